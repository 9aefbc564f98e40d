#!/usr/bin/env bash
# Offline validation of the deployment files (no Docker daemon, no cluster needed):
#   bash deploy/validate.sh
# The validators come from PyPI into two private virtualenvs (their jsonschema versions
# conflict): docker-compose 1.29 (its PyYAML 5.4 needs Cython < 3 to build) and
# kubernetes-validate. CVFARM_DEPLOY_TOOLS chooses where they live.
set -euo pipefail
cd "$(dirname "$0")/.."
TOOLS="${CVFARM_DEPLOY_TOOLS:-${HOME:-/tmp}/.cache/cvfarm-deploy-tools}"
if [ ! -x "$TOOLS/compose/bin/docker-compose" ]; then
  python3 -m venv "$TOOLS/compose"
  "$TOOLS/compose/bin/pip" install -q "cython<3" wheel
  "$TOOLS/compose/bin/pip" install -q --no-build-isolation "pyyaml==5.4.1"
  "$TOOLS/compose/bin/pip" install -q "docker-compose==1.29.2"
fi
if [ ! -x "$TOOLS/k8s/bin/kubernetes-validate" ]; then
  python3 -m venv "$TOOLS/k8s"
  "$TOOLS/k8s/bin/pip" install -q kubernetes-validate
fi
# Compose: schema and interpolation (the defaults stand in for unset tokens).
"$TOOLS/compose/bin/docker-compose" -f docker-compose.yml config -q
# Kubernetes: every manifest against the API schemas (strict: unknown fields are errors).
"$TOOLS/k8s/bin/kubernetes-validate" --strict deploy/k8s/*.yaml
echo "deployment files valid"
