-- cvfarm coordinator schema, PostgreSQL flavour (kept column-for-column in step with ../sqlite).
-- Never edit an applied migration: add a new file.

-- A job: the submitted spec and its resolved settings; `phase_idx` is the active phase.
CREATE TABLE jobs (
    id          BIGSERIAL PRIMARY KEY,
    spec        TEXT    NOT NULL,           -- JobSpec JSON (scene replaced by its bundle hash)
    resolved    TEXT    NOT NULL,           -- ResolvedJob JSON
    scene_hash  TEXT    NOT NULL,
    estimator   TEXT    NOT NULL,
    effects     TEXT    NOT NULL,           -- JSON list of the effects the scene calls for
    priority    BIGINT  NOT NULL,
    state       TEXT    NOT NULL,           -- running | done | failed | cancelled
    phase_idx   BIGINT  NOT NULL,
    error       TEXT,
    created_ms  BIGINT  NOT NULL,
    finished_ms BIGINT
);
CREATE INDEX jobs_queue ON jobs (state, priority DESC, id);

-- Phases of a job, in order (render only, for now; train/solve/render for CV jobs later).
CREATE TABLE phases (
    job_id       BIGINT NOT NULL REFERENCES jobs (id),
    idx          BIGINT NOT NULL,
    name         TEXT   NOT NULL,           -- surrogate | train | render
    coefficients TEXT,                      -- content address of the coefficient table it renders with
    started_ms   BIGINT,
    finished_ms  BIGINT,
    PRIMARY KEY (job_id, idx)
);

-- Tile tasks: a rectangle and a sample range of one phase; `seq` is the canonical order.
CREATE TABLE tasks (
    id               BIGSERIAL PRIMARY KEY,
    job_id           BIGINT NOT NULL REFERENCES jobs (id),
    phase_idx        BIGINT NOT NULL,
    seq              BIGINT NOT NULL,
    x0               BIGINT NOT NULL,
    y0               BIGINT NOT NULL,
    width            BIGINT NOT NULL,
    height           BIGINT NOT NULL,
    sample_start     BIGINT NOT NULL,
    sample_end       BIGINT NOT NULL,
    state            TEXT   NOT NULL,       -- pending | leased | done
    attempt          BIGINT NOT NULL DEFAULT 0,  -- attempt number of the current/last lease
    worker_id        BIGINT,
    lease_expires_ms BIGINT,
    failures         BIGINT NOT NULL DEFAULT 0,  -- expired or failed attempts
    done_attempt     BIGINT,
    done_ms          BIGINT,
    UNIQUE (job_id, phase_idx, seq)
);
CREATE INDEX tasks_claim ON tasks (state, job_id, phase_idx, seq);
CREATE INDEX tasks_lease ON tasks (state, lease_expires_ms);

-- Accepted results, one per task, keyed by (task, attempt): the validated frame stream.
CREATE TABLE results (
    task_id    BIGINT NOT NULL REFERENCES tasks (id),
    attempt    BIGINT NOT NULL,
    data       BYTEA   NOT NULL,
    created_ms BIGINT NOT NULL,
    PRIMARY KEY (task_id, attempt)
);

-- Registered workers; only the SHA-256 of each secret is kept.
CREATE TABLE workers (
    id           BIGSERIAL PRIMARY KEY,
    name         TEXT   NOT NULL,
    secret_hash  TEXT   NOT NULL,
    created_ms   BIGINT NOT NULL,
    last_seen_ms BIGINT NOT NULL
);

-- Failures of a worker on a job: at the cap, the worker is blocked for that job.
CREATE TABLE worker_job_failures (
    job_id    BIGINT NOT NULL,
    worker_id BIGINT NOT NULL,
    failures  BIGINT NOT NULL,
    PRIMARY KEY (job_id, worker_id)
);

-- Content-addressed blobs: scene documents and assets (sha256 hex).
CREATE TABLE blobs (
    hash       TEXT   PRIMARY KEY,
    data       BYTEA   NOT NULL,
    created_ms BIGINT NOT NULL
);

-- Finished outputs of a job: image.exr, preview.png, stats.json.
CREATE TABLE artifacts (
    job_id       BIGINT NOT NULL REFERENCES jobs (id),
    name         TEXT   NOT NULL,
    content_type TEXT   NOT NULL,
    data         BYTEA   NOT NULL,
    PRIMARY KEY (job_id, name)
);
