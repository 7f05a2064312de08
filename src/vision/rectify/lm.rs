//! Levenberg–Marquardt (Marquardt's diagonal damping) with a central-difference Jacobian, for
//! the six unknowns of the quasi-Euclidean rectification (Fusiello & Irsara 2008).

use nalgebra::SMatrix;
use rayon::prelude::*;

/// How [`minimise`] runs.
pub(super) struct Options {
    /// Iterations at most.
    pub max_iterations: usize,
    /// Stop when a step lowers the cost by less than this fraction.
    pub tolerance: f64,
    /// Only the first `n_free` unknowns move.
    pub n_free: usize,
    /// Largest change of each unknown in one step (the whole step is scaled down to it).
    pub max_step: [f64; 6],
    /// Bounds of the last unknown.
    pub last_range: (f64, f64),
}

/// Minimises the sum of squares of `residuals(p)` (written into the buffer) from `start`; the
/// minimiser and the iterations used.
pub(super) fn minimise(
    residuals: impl Fn(&[f64; 6], &mut Vec<f64>) + Sync,
    start: [f64; 6],
    opts: &Options,
) -> ([f64; 6], usize) {
    let n_free = opts.n_free;
    let clamp_last = |mut v: [f64; 6]| {
        v[5] = v[5].clamp(opts.last_range.0, opts.last_range.1);
        v
    };
    let mut p = clamp_last(start);
    let mut r = Vec::new();
    let mut r_try = Vec::new();
    let cost = |v: &[f64; 6], buf: &mut Vec<f64>| {
        residuals(v, buf);
        buf.iter().map(|x| x * x).sum::<f64>()
    };
    let mut c = cost(&p, &mut r);
    let mut lambda = 1e-3;
    let mut it = 0;
    while it < opts.max_iterations {
        it += 1;
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        let mut jtr = SMatrix::<f64, 6, 1>::zeros();
        // Jacobian columns by central differences, each on its own: computed at the same time.
        let cols: Vec<Vec<f64>> = (0..6)
            .into_par_iter()
            .map(|k| {
                if k >= n_free {
                    return vec![0.0; r.len()];
                }
                let step = 1e-6;
                let (mut a, mut b) = (p, p);
                a[k] += step;
                b[k] -= step;
                let (mut r_plus, mut r_minus) = (Vec::new(), Vec::new());
                residuals(&a, &mut r_plus);
                residuals(&b, &mut r_minus);
                r_plus
                    .iter()
                    .zip(&r_minus)
                    .map(|(u, v)| (u - v) / (2.0 * step))
                    .collect()
            })
            .collect();
        for a in 0..6 {
            jtr[a] = cols[a].iter().zip(&r).map(|(j, e)| j * e).sum();
            for b in a..6 {
                let v: f64 = cols[a].iter().zip(&cols[b]).map(|(x, y)| x * y).sum();
                jtj[(a, b)] = v;
                jtj[(b, a)] = v;
            }
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut damped = jtj;
            for d in 0..6 {
                damped[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
                if d >= n_free {
                    damped[(d, d)] = 1.0;
                }
            }
            let Some(delta) = damped.cholesky().map(|ch| ch.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let scale = (0..6)
                .map(|k| delta[k].abs() / opts.max_step[k])
                .fold(1.0f64, f64::max);
            let mut trial = p;
            for k in 0..6 {
                trial[k] += delta[k] / scale;
            }
            let trial = clamp_last(trial);
            let ct = cost(&trial, &mut r_try);
            if ct < c {
                let rel = (c - ct) / c.max(1e-300);
                p = trial;
                c = ct;
                std::mem::swap(&mut r, &mut r_try);
                lambda = (lambda / 10.0).max(1e-15);
                improved = true;
                if rel < opts.tolerance {
                    return (p, it);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (p, it)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sum of squares with its minimum inside the bounds is found; a frozen unknown stays,
    /// the last one stays inside its range.
    #[test]
    fn finds_the_minimum_of_a_sum_of_squares() {
        let target = [0.3, -0.2, 0.05, 0.0, 0.1, 2.0];
        let residuals = |v: &[f64; 6], out: &mut Vec<f64>| {
            out.clear();
            out.extend(v.iter().zip(&target).map(|(a, b)| a - b));
        };
        let opts = Options {
            max_iterations: 200,
            tolerance: 1e-15,
            n_free: 6,
            max_step: [0.1, 0.1, 0.1, 0.1, 0.1, 0.5],
            last_range: (-2.0, 10.0),
        };
        let (p, _) = minimise(residuals, [0.0; 6], &opts);
        for (a, b) in p.iter().zip(&target) {
            assert!((a - b).abs() < 1e-6, "{p:?}");
        }
        let (p, _) = minimise(residuals, [0.0; 6], &Options { n_free: 5, ..opts });
        assert_eq!(p[5], 0.0);
        let (p, _) = minimise(
            residuals,
            [0.0; 6],
            &Options {
                last_range: (-2.0, 1.0),
                ..opts
            },
        );
        assert!(p[5] <= 1.0 && (p[5] - 1.0).abs() < 1e-6, "{p:?}");
    }

    /// The Jacobian's columns computed at the same time give the minimiser of one thread, to
    /// the bit.
    #[test]
    fn the_parallel_jacobian_gives_the_serial_result() {
        let points: Vec<f64> = (0..300).map(|i| f64::from(i) * 0.37 % 11.0).collect();
        let residuals = |v: &[f64; 6], out: &mut Vec<f64>| {
            out.clear();
            out.extend(points.iter().map(|&x| {
                (v[0] - 0.3).sin() * x + (v[1] * x).tanh() + v[2] * v[3] - 0.7 + v[4] * x * x * 1e-3
                    - (v[5] - 1.5).powi(3)
            }));
        };
        let opts = Options {
            max_iterations: 50,
            tolerance: 1e-14,
            n_free: 6,
            max_step: [0.1; 6],
            last_range: (-3.0, 3.0),
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| minimise(residuals, [0.1; 6], &opts));
        let many = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap()
            .install(|| minimise(residuals, [0.1; 6], &opts));
        assert!(one.1 > 1);
        assert_eq!(one.0.map(f64::to_bits), many.0.map(f64::to_bits));
        assert_eq!(one.1, many.1);
    }
}
