//! 1-D mixture-sampling harness on [0, 1] shared by the integration tests.
#![allow(dead_code)]

use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample};
use estimators::solve::{CellCoefficients, SolvePolicy, solve};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Normalised densities on [0, 1].
#[derive(Clone, Copy, Debug)]
pub enum Pdf {
    /// 1.
    Uniform,
    /// 2x.
    Linear,
    /// 2(1 − x).
    LinearDown,
    /// 3x².
    Quadratic,
    /// Uniform on [a, b].
    Box(f64, f64),
    /// π sin(2πx) on [0, ½].
    SinPos,
    /// −π sin(2πx) on [½, 1].
    SinNeg,
}

impl Pdf {
    pub fn pdf(self, x: f64) -> f64 {
        use std::f64::consts::PI;
        match self {
            Pdf::Uniform => 1.0,
            Pdf::Linear => 2.0 * x,
            Pdf::LinearDown => 2.0 * (1.0 - x),
            Pdf::Quadratic => 3.0 * x * x,
            Pdf::Box(a, b) => {
                if (a..b).contains(&x) {
                    1.0 / (b - a)
                } else {
                    0.0
                }
            }
            Pdf::SinPos => {
                if x < 0.5 {
                    PI * (2.0 * PI * x).sin()
                } else {
                    0.0
                }
            }
            Pdf::SinNeg => {
                if x >= 0.5 {
                    -PI * (2.0 * PI * x).sin()
                } else {
                    0.0
                }
            }
        }
    }

    pub fn sample(self, u: f64) -> f64 {
        use std::f64::consts::PI;
        match self {
            Pdf::Uniform => u,
            Pdf::Linear => u.sqrt(),
            Pdf::LinearDown => 1.0 - (1.0 - u).sqrt(),
            Pdf::Quadratic => u.cbrt(),
            Pdf::Box(a, b) => a + (b - a) * u,
            // CDF (1 − cos 2πx)/2 on [0, ½].
            Pdf::SinPos => (1.0 - 2.0 * u).acos() / (2.0 * PI),
            Pdf::SinNeg => 0.5 + (1.0 - 2.0 * u).acos() / (2.0 * PI),
        }
        .clamp(0.0, 1.0 - 1e-16)
    }
}

pub type Integrand = fn(f64) -> [f64; 3];

/// A mixture of components with selection probabilities; all components partitioned
/// (non-overlapping supports) or all overlapping.
#[derive(Clone)]
pub struct Setup {
    pub comps: Vec<Pdf>,
    pub select: Vec<f64>,
    pub partitioned: bool,
    pub f: Integrand,
}

pub struct Draw {
    pub x: f64,
    pub pdf: f64,
    pub lambdas: Vec<f64>,
    pub value: [f64; 3],
}

impl Setup {
    pub fn layout(&self) -> ComponentLayout {
        let n = self.comps.len() as u32;
        if self.partitioned {
            ComponentLayout::new(n, 0).unwrap()
        } else {
            ComponentLayout::new(0, n).unwrap()
        }
    }

    pub fn draw(&self, rng: &mut Pcg64) -> Draw {
        let u: f64 = rng.random();
        let mut acc = 0.0;
        let mut j = self.comps.len() - 1;
        for (i, c) in self.select.iter().enumerate() {
            acc += c;
            if u < acc {
                j = i;
                break;
            }
        }
        let x = self.comps[j].sample(rng.random());
        let lambdas: Vec<f64> = self.comps.iter().map(|p| p.pdf(x)).collect();
        let pdf: f64 = lambdas.iter().zip(&self.select).map(|(l, c)| l * c).sum();
        let fx = (self.f)(x);
        Draw {
            x,
            pdf,
            value: fx.map(|v| v / pdf),
            lambdas,
        }
    }

    pub fn sample_view<'a>(&self, d: &'a Draw) -> CvSample<'a> {
        if self.partitioned {
            let k = d.lambdas.iter().position(|&l| l > 0.0);
            CvSample {
                pdf: d.pdf,
                partition: k.map(|k| (k as u32, d.lambdas[k])),
                overlapping: &[],
            }
        } else {
            CvSample {
                pdf: d.pdf,
                partition: None,
                overlapping: &d.lambdas,
            }
        }
    }

    pub fn train(
        &self,
        n: usize,
        seed: u64,
        color: ColorMode,
        policy: &SolvePolicy,
    ) -> CellCoefficients {
        let mut rng = Pcg64::seed_from_u64(seed);
        let mut acc = CellAccumulator::new(self.layout(), color);
        for _ in 0..n {
            let d = self.draw(&mut rng);
            acc.add(1.0, d.value, &self.sample_view(&d)).unwrap();
        }
        solve(&acc, policy)
    }

    /// Per-sample CV estimates `Σα + F − Σ α λ / p` (one sample per estimate).
    pub fn estimates(&self, coeffs: &CellCoefficients, n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = Pcg64::seed_from_u64(seed);
        let s = coeffs.alpha_sum();
        (0..n)
            .map(|_| {
                let d = self.draw(&mut rng);
                let v = coeffs.apply(d.value, &self.sample_view(&d));
                [v[0] + s[0], v[1] + s[1], v[2] + s[2]]
            })
            .collect()
    }
}

/// Mean and (unbiased) variance per channel.
pub fn mean_var(v: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let n = v.len() as f64;
    let mut m = [0.0; 3];
    for x in v {
        for c in 0..3 {
            m[c] += x[c] / n;
        }
    }
    let mut var = [0.0; 3];
    for x in v {
        for c in 0..3 {
            var[c] += (x[c] - m[c]).powi(2) / (n - 1.0);
        }
    }
    (m, var)
}

pub fn sum3(a: [f64; 3]) -> f64 {
    a[0] + a[1] + a[2]
}
