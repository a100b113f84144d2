//! Fixed-step ODE samplers for flow matching (Motion Flow Matching: dongzhuoyao/motionfm
//! `flow/flow_matching_class.py`; docs/official/motionfm.md#euler-sampler).
//!
//! Time runs from t = 0 (noise) to t = 1 (data) on the uniform grid t_k = k / N, computed as an
//! f32 division like the official custom loops. A step integrates dx/dt = v(x, t) from t_k to
//! t_{k+1}: Euler uses one velocity evaluation, Heun (trapezoidal predictor-corrector) and the
//! midpoint rule two. Guidance, when used, is applied to each velocity by the caller.

use crate::error::{invalid_arg, Error, Result};

/// The caller's (guided) velocity field: `velocity(t, x, v)` writes v(x, t) into `v`.
pub type Velocity<'a> = dyn FnMut(f32, &[f32], &mut [f32]) -> Result<()> + 'a;

/// The integration rule of a flow sampler.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OdeMethod {
    /// x ← x + dt·v(x, t): the paper's sampler.
    Euler,
    /// Predictor x' = x + dt·v(x, t), then x ← x + dt/2·(v(x, t) + v(x', t + dt)).
    Heun,
    /// x ← x + dt·v(x + dt/2·v(x, t), t + dt/2).
    Midpoint,
}

impl std::str::FromStr for OdeMethod {
    type Err = Error;
    fn from_str(s: &str) -> Result<OdeMethod> {
        match s {
            "euler" => Ok(OdeMethod::Euler),
            "heun" => Ok(OdeMethod::Heun),
            "midpoint" => Ok(OdeMethod::Midpoint),
            _ => Err(invalid_arg!(
                "unknown ODE method `{s}` (euler, heun, midpoint)"
            )),
        }
    }
}

/// A fixed-grid flow-matching sampler over `steps` steps.
#[derive(Clone, Debug)]
pub struct FlowSampler {
    method: OdeMethod,
    steps: usize,
}

impl FlowSampler {
    /// A sampler integrating from t = 0 to 1 in `steps` equal steps of `method`; zero steps is
    /// an `InvalidArgument`.
    pub fn new(method: OdeMethod, steps: usize) -> Result<FlowSampler> {
        if steps == 0 {
            return Err(invalid_arg!("a flow sampler needs at least one step"));
        }
        Ok(FlowSampler { method, steps })
    }

    /// The integration rule.
    pub fn method(&self) -> OdeMethod {
        self.method
    }

    /// N, the steps from noise to data; the network runs N ×
    /// [`FlowSampler::evaluations_per_step`] times (twice that with guidance).
    pub fn num_steps(&self) -> usize {
        self.steps
    }

    /// Grid time t_k = k / N (f32 division, as the official loops compute it).
    pub fn time(&self, k: usize) -> f32 {
        k as f32 / self.steps as f32
    }

    /// Velocity evaluations per step (1 for Euler, 2 otherwise).
    pub fn evaluations_per_step(&self) -> usize {
        match self.method {
            OdeMethod::Euler => 1,
            OdeMethod::Heun | OdeMethod::Midpoint => 2,
        }
    }

    /// Step `k` (0..N) from `x` at t_k to `x_next` at t_{k+1}. `velocity(t, x, v)` writes the
    /// (guided) velocity at `(x, t)` into `v`; `scratch` holds intermediate points. Also writes
    /// the clean-motion estimate `x + (1 − t_k)·v(x, t_k)` (the straight path's end) into `x1`.
    pub fn step(
        &self,
        k: usize,
        x: &[f32],
        velocity: &mut Velocity,
        scratch: &mut FlowScratch,
        x_next: &mut [f32],
        x1: &mut [f32],
    ) -> Result<()> {
        if k >= self.steps {
            return Err(invalid_arg!(
                "flow step {k} does not exist: the sampler takes {} steps, counted from 0",
                self.steps
            ));
        }
        let n = x.len();
        if x_next.len() != n || x1.len() != n {
            return Err(invalid_arg!("flow step buffers must all have {n} values"));
        }
        let t = self.time(k);
        let t_next = self.time(k + 1);
        let dt = t_next - t;
        scratch.v1.resize(n, 0.0);
        velocity(t, x, &mut scratch.v1)?;
        for ((e, &xi), &v) in x1.iter_mut().zip(x).zip(&scratch.v1) {
            *e = xi + (1.0 - t) * v;
        }
        match self.method {
            OdeMethod::Euler => {
                for ((o, &xi), &v) in x_next.iter_mut().zip(x).zip(&scratch.v1) {
                    *o = xi + dt * v;
                }
            }
            OdeMethod::Heun => {
                scratch.point.clear();
                scratch
                    .point
                    .extend(x.iter().zip(&scratch.v1).map(|(&xi, &v)| xi + dt * v));
                scratch.v2.resize(n, 0.0);
                velocity(t_next, &scratch.point, &mut scratch.v2)?;
                for (((o, &xi), &a), &b) in
                    x_next.iter_mut().zip(x).zip(&scratch.v1).zip(&scratch.v2)
                {
                    *o = xi + 0.5 * dt * (a + b);
                }
            }
            OdeMethod::Midpoint => {
                let half = 0.5 * dt;
                scratch.point.clear();
                scratch
                    .point
                    .extend(x.iter().zip(&scratch.v1).map(|(&xi, &v)| xi + half * v));
                scratch.v2.resize(n, 0.0);
                velocity(t + half, &scratch.point, &mut scratch.v2)?;
                for ((o, &xi), &v) in x_next.iter_mut().zip(x).zip(&scratch.v2) {
                    *o = xi + dt * v;
                }
            }
        }
        Ok(())
    }
}

/// Intermediate buffers of a flow step, reused across steps.
#[derive(Default, Debug)]
pub struct FlowScratch {
    v1: Vec<f32>,
    v2: Vec<f32>,
    point: Vec<f32>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Integrates dx/dt = f(x, t) over N steps from x0 and returns the end point.
    fn integrate(method: OdeMethod, n: usize, x0: f32, f: impl Fn(f32, f32) -> f32) -> f32 {
        let s = FlowSampler::new(method, n).unwrap();
        let mut x = vec![x0];
        let mut next = vec![0.0];
        let mut x1 = vec![0.0];
        let mut scratch = FlowScratch::default();
        let mut vel = |t: f32, x: &[f32], v: &mut [f32]| {
            v[0] = f(x[0], t);
            Ok(())
        };
        for k in 0..n {
            s.step(k, &x, &mut vel, &mut scratch, &mut next, &mut x1)
                .unwrap();
            std::mem::swap(&mut x, &mut next);
        }
        x[0]
    }

    #[test]
    fn grid_is_k_over_n_in_f32() {
        let s = FlowSampler::new(OdeMethod::Euler, 10).unwrap();
        assert_eq!(s.time(0), 0.0);
        assert_eq!(s.time(3), 3.0f32 / 10.0f32);
        assert_eq!(s.time(10), 1.0);
        // For N = 50 and 100 the official index trunc(t·1000) is exactly 1000·k/N
        // (docs/official/motionfm.md#time-index).
        for n in [50usize, 100] {
            let s = FlowSampler::new(OdeMethod::Euler, n).unwrap();
            for k in 0..n {
                assert_eq!((s.time(k) * 1000.0) as usize, 1000 * k / n, "N {n}, k {k}");
            }
        }
    }

    #[test]
    fn constant_velocity_is_exact_for_every_method() {
        // The straight path of flow matching: v = x1 − x0 constant, so x(1) = x0 + v.
        for m in [OdeMethod::Euler, OdeMethod::Heun, OdeMethod::Midpoint] {
            let end = integrate(m, 7, 0.25, |_, _| 1.5);
            assert!((end - 1.75).abs() < 1e-6, "{m:?}: {end}");
        }
    }

    #[test]
    fn orders_on_dx_dt_equals_x() {
        // dx/dt = x from x(0) = 1 with step h = 1/N: Euler gives (1 + h)^N, Heun and midpoint
        // both give (1 + h + h²/2)^N (hand-derived; both are second order).
        let n = 4;
        let h = 0.25f64;
        let euler = (1.0 + h).powi(n as i32);
        let second = (1.0 + h + h * h / 2.0).powi(n as i32);
        assert!((integrate(OdeMethod::Euler, n, 1.0, |x, _| x) as f64 - euler).abs() < 1e-5);
        assert!((integrate(OdeMethod::Heun, n, 1.0, |x, _| x) as f64 - second).abs() < 1e-5);
        assert!((integrate(OdeMethod::Midpoint, n, 1.0, |x, _| x) as f64 - second).abs() < 1e-5);
        // And they are closer to e than Euler.
        assert!((second - std::f64::consts::E).abs() < (euler - std::f64::consts::E).abs());
    }

    #[test]
    fn time_dependent_velocity_uses_the_right_times() {
        // dx/dt = t: exact x(1) = x0 + 1/2. Heun (trapezoid) and midpoint are exact for a
        // linear-in-t velocity; Euler gives the left Riemann sum Σ k/N² = (N−1)/(2N).
        let n = 5;
        assert!((integrate(OdeMethod::Heun, n, 0.0, |_, t| t) - 0.5).abs() < 1e-6);
        assert!((integrate(OdeMethod::Midpoint, n, 0.0, |_, t| t) - 0.5).abs() < 1e-6);
        let euler = integrate(OdeMethod::Euler, n, 0.0, |_, t| t);
        assert!((euler - 0.4).abs() < 1e-6, "{euler}");
    }

    #[test]
    fn estimate_and_errors() {
        let s = FlowSampler::new(OdeMethod::Euler, 4).unwrap();
        let mut scratch = FlowScratch::default();
        let (mut next, mut x1) = (vec![0.0; 2], vec![0.0; 2]);
        let mut vel = |_: f32, _: &[f32], v: &mut [f32]| {
            v.copy_from_slice(&[2.0, -1.0]);
            Ok(())
        };
        s.step(1, &[0.5, 0.5], &mut vel, &mut scratch, &mut next, &mut x1)
            .unwrap();
        // t_1 = 0.25: x1 = x + 0.75·v.
        assert_eq!(x1, vec![2.0, -0.25]);
        assert_eq!(next, vec![1.0, 0.25]);
        assert!(s
            .step(4, &[0.5, 0.5], &mut vel, &mut scratch, &mut next, &mut x1)
            .is_err());
        assert!(s
            .step(0, &[0.5], &mut vel, &mut scratch, &mut next, &mut x1)
            .is_err());
        assert!(FlowSampler::new(OdeMethod::Heun, 0).is_err());
        assert!("rk4".parse::<OdeMethod>().is_err());
    }
}
