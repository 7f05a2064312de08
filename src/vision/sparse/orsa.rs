//! ORSA / AC-RANSAC: RANSAC scored by the number of false alarms, with an automatic
//! inlier threshold (Moisan & Stival, IJCV 2004; Moisan, Moulon & Monasse, "Automatic
//! Homographic Registration of a Pair of Images, with A Contrario Elimination of
//! Outliers", IPOL 2012, and "Fundamental Matrix of a Stereo Pair, with A Contrario
//! Elimination of Outliers", IPOL 2016).
//!
//! For a model and its residuals sorted as `e_(1) ≤ … ≤ e_(n)`, the NFA of keeping the `k`
//! best matches is (IPOL 2016, eq. 3)
//!
//! `NFA(k) = N_s · (n − m) · C(n, k) · C(k, m) · α(e_(k))^(k − m)`,
//!
//! where `m` is the minimal sample size, `N_s` the number of models one sample can give and
//! `α(ε) = 2·D·ε / A` the probability that a uniformly random point of an image of diameter
//! `D` and area `A` lies within `ε` of a given line. The model is meaningful when
//! `min_k log10 NFA < 0`; the minimising `e_(k)` is its inlier threshold.

use nalgebra::{Matrix3, Vector2};
use rand::SeedableRng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::sparse::fundamental::{FundamentalModel, symmetric_epipolar_error};

/// Parameters of ORSA.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OrsaParams {
    /// Most random samples drawn, reserve included (default 10 000, as the IPOL code).
    pub max_iterations: usize,
    /// Fraction of `max_iterations` kept to resample from the best inlier set once a meaningful
    /// model is found (default 0.1, IPOL's "10 % reserved for refinement").
    pub reserve_fraction: f64,
    /// Stop sampling early once a sample of inliers has been drawn with this probability,
    /// given the inlier ratio of the best model (default 0.9999; 1.0 always draws
    /// `max_iterations`). Samples go in fixed batches, so the result stays deterministic.
    pub confidence: f64,
    /// Seed of the random generator: the same seed and input give the same result (default 0).
    pub seed: u64,
    /// Largest inlier threshold considered, pixels (default none: fully automatic).
    pub max_threshold_px: Option<f64>,
    /// Which fundamental matrix is fitted (default `projective`, the paper's; `affine` is
    /// exact for SEM's parallel projection).
    pub model: FundamentalModel,
}

impl Default for OrsaParams {
    fn default() -> Self {
        Self {
            max_iterations: 10_000,
            reserve_fraction: 0.1,
            confidence: 0.9999,
            seed: 0,
            max_threshold_px: None,
            model: FundamentalModel::Projective,
        }
    }
}

/// A meaningful model found by ORSA.
#[derive(Debug, Clone, PartialEq)]
pub struct OrsaResult {
    /// The fundamental matrix, `x'ᵀ F x = 0`, Frobenius norm 1.
    pub f: Matrix3<f64>,
    /// Indices of the inlier matches, ascending.
    pub inliers: Vec<usize>,
    /// log10 of the number of false alarms (< 0).
    pub log10_nfa: f64,
    /// The automatic inlier threshold: largest symmetric epipolar distance kept, pixels.
    pub threshold_px: f64,
    /// Samples drawn.
    pub iterations: usize,
}

/// Why ORSA found no model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OrsaError {
    #[error("not enough matches for ORSA: found {found}, need more than {need}")]
    TooFewMatches { found: usize, need: usize },
    #[error(
        "no meaningful epipolar geometry: best log10 NFA = {best_log10_nfa:.1} with {inliers} matches (must be < 0)"
    )]
    NotMeaningful { best_log10_nfa: f64, inliers: usize },
}

/// log10 of the combinatorial factors of the NFA, tabulated once.
struct NfaTable {
    m: usize,
    /// log10(N_s · (n − m)).
    log_e0: f64,
    /// log10 α(1 px).
    log_alpha0: f64,
    /// log10 C(n, k), k = 0 … n.
    log_c_n: Vec<f64>,
    /// log10 C(k, m), k = 0 … n.
    log_c_k: Vec<f64>,
}

fn log10_factorials(n: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(n + 1);
    let mut acc = 0.0;
    out.push(0.0);
    for i in 1..=n {
        acc += (i as f64).log10();
        out.push(acc);
    }
    out
}

impl NfaTable {
    fn new(n: usize, m: usize, n_s: usize, log_alpha0: f64) -> Self {
        let lf = log10_factorials(n);
        let log_c_n = (0..=n).map(|k| lf[n] - lf[k] - lf[n - k]).collect();
        let log_c_k = (0..=n)
            .map(|k| {
                if k < m {
                    0.0
                } else {
                    lf[k] - lf[m] - lf[k - m]
                }
            })
            .collect();
        Self {
            m,
            log_e0: ((n_s * (n - m)) as f64).log10(),
            log_alpha0,
            log_c_n,
            log_c_k,
        }
    }

    /// `(log10 NFA, k)` of the best prefix of `sorted` residuals (ascending); `k` counts the
    /// matches kept. `None` when fewer than `m + 1` residuals.
    fn best(&self, sorted: &[f64]) -> Option<(f64, usize)> {
        let mut best: Option<(f64, usize)> = None;
        for k in self.m + 1..=sorted.len() {
            // Floor ε so exact data stays finite; α is a probability, at most 1.
            let log_alpha = (self.log_alpha0 + sorted[k - 1].max(1e-9).log10()).min(0.0);
            let nfa =
                self.log_e0 + log_alpha * (k - self.m) as f64 + self.log_c_n[k] + self.log_c_k[k];
            if best.is_none_or(|(b, _)| nfa < b) {
                best = Some((nfa, k));
            }
        }
        best
    }
}

/// The best model of one sample or batch: (log10 NFA, inlier count, threshold, F).
#[derive(Debug, Clone)]
struct Candidate {
    log10_nfa: f64,
    k: usize,
    threshold: f64,
    f: Matrix3<f64>,
}

/// A test a model must pass to be scored at all (prior knowledge of the geometry, such as the
/// direction of the tilt axis): `true` keeps it.
pub type ModelFilter<'a> = &'a (dyn Fn(&Matrix3<f64>) -> bool + Sync);

struct Problem<'a> {
    left: &'a [Vector2<f64>],
    right: &'a [Vector2<f64>],
    model: FundamentalModel,
    table: NfaTable,
    max_threshold: f64,
    filter: Option<ModelFilter<'a>>,
}

impl Problem<'_> {
    /// Scores `f` on all matches; `buf` is scratch space. `None` for a model the filter
    /// refuses.
    fn score(&self, f: &Matrix3<f64>, buf: &mut Vec<f64>) -> Option<Candidate> {
        if self.filter.is_some_and(|keep| !keep(f)) {
            return None;
        }
        buf.clear();
        buf.extend(
            self.left
                .iter()
                .zip(self.right)
                .map(|(x, xp)| symmetric_epipolar_error(f, x, xp))
                .filter(|e| *e <= self.max_threshold),
        );
        buf.sort_unstable_by(f64::total_cmp);
        let (log10_nfa, k) = self.table.best(buf)?;
        Some(Candidate {
            log10_nfa,
            k,
            threshold: buf[k - 1],
            f: *f,
        })
    }

    fn inliers(&self, c: &Candidate) -> Vec<usize> {
        (0..self.left.len())
            .filter(|&i| {
                symmetric_epipolar_error(&c.f, &self.left[i], &self.right[i]) <= c.threshold
            })
            .collect()
    }
}

/// Sample `iteration` from `pool`: its own generator, seeded from `(seed, iteration)`, so batches
/// can run in parallel and still repeat exactly.
fn draw(seed: u64, iteration: usize, pool: &[usize], m: usize) -> Vec<usize> {
    // SplitMix64 of the pair: well-spread seeds for neighbouring iterations.
    let mut z = seed ^ (iteration as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(z);
    rand::seq::index::sample(&mut rng, pool.len(), m)
        .into_iter()
        .map(|i| pool[i])
        .collect()
}

const BATCH: usize = 64;

/// Any two of the sampled points closer than 1 px.
fn has_coincident_points(points: &[Vector2<f64>], idx: &[usize]) -> bool {
    idx.iter().enumerate().any(|(k, &i)| {
        idx[..k]
            .iter()
            .any(|&j| (points[i] - points[j]).norm_squared() < 1.0)
    })
}

/// Runs batches of samples from `pool` with iteration numbers `first..first + budget`,
/// improving `best`; returns the number of samples drawn.
fn sample_phase(
    p: &Problem<'_>,
    params: &OrsaParams,
    pool: &[usize],
    first: usize,
    budget: usize,
    best: &mut Option<Candidate>,
) -> usize {
    let m = p.model.sample_size();
    let n = p.left.len();
    let mut done = 0;
    while done < budget {
        let end = (done + BATCH).min(budget);
        let batch: Vec<Option<Candidate>> = (done..end)
            .into_par_iter()
            .map_init(Vec::new, |buf, it| {
                let idx = draw(params.seed, first + it, pool, m);
                // Two matches at the same place in either image make the sample degenerate: the
                // solver then fits a family of models that explains nothing.
                if has_coincident_points(p.left, &idx) || has_coincident_points(p.right, &idx) {
                    return None;
                }
                p.model
                    .fit_minimal(p.left, p.right, &idx)
                    .iter()
                    .filter_map(|f| p.score(f, buf))
                    .fold(None, |acc: Option<Candidate>, c| match acc {
                        Some(a) if a.log10_nfa <= c.log10_nfa => Some(a),
                        _ => Some(c),
                    })
            })
            .collect();
        // In iteration order, strict improvement only: independent of scheduling.
        for c in batch.into_iter().flatten() {
            if best.as_ref().is_none_or(|b| c.log10_nfa < b.log10_nfa) {
                *best = Some(c);
            }
        }
        done = end;
        if let Some(b) = best.as_ref().filter(|b| b.log10_nfa < 0.0)
            && params.confidence < 1.0
        {
            let w = (b.k as f64 / n as f64).powi(m as i32);
            let needed = if w >= 1.0 {
                1.0
            } else {
                (1.0 - params.confidence).ln() / (1.0 - w).ln()
            };
            if (done as f64) >= needed {
                break;
            }
        }
    }
    done
}

/// Finds the fundamental matrix of `left[i] ↔ right[i]` with the lowest NFA.
///
/// `image_sizes` are the left and right image sizes `(w, h)`, for α. After the random
/// phase and the resampling of the best inlier set, the model is refitted by least squares on
/// its inliers and the refit is kept when its NFA is lower.
///
/// # Errors
/// [`OrsaError::TooFewMatches`] with at most `m` matches, [`OrsaError::NotMeaningful`] when no
/// model reaches log10 NFA < 0.
pub fn orsa(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    image_sizes: [(usize, usize); 2],
    params: &OrsaParams,
) -> Result<OrsaResult, OrsaError> {
    orsa_filtered(left, right, image_sizes, params, None)
}

/// [`orsa`] among the models that pass `filter` only: models the prior knowledge rules out
/// are never scored, so a consistent set of wrong matches (a repetitive scene, or a nearly flat
/// specimen whose matches leave the epipolar direction undetermined) cannot win.
///
/// # Errors
/// As [`orsa`].
pub fn orsa_filtered(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    image_sizes: [(usize, usize); 2],
    params: &OrsaParams,
    filter: Option<ModelFilter<'_>>,
) -> Result<OrsaResult, OrsaError> {
    let n = left.len().min(right.len());
    let m = params.model.sample_size();
    if n <= m {
        return Err(OrsaError::TooFewMatches { found: n, need: m });
    }
    let log_alpha0 = image_sizes
        .iter()
        .map(|&(w, h)| {
            let (w, h) = (w.max(1) as f64, h.max(1) as f64);
            (2.0 * w.hypot(h) / (w * h)).log10()
        })
        .fold(f64::NEG_INFINITY, f64::max);
    let p = Problem {
        left: &left[..n],
        right: &right[..n],
        model: params.model,
        table: NfaTable::new(n, m, params.model.max_models(), log_alpha0),
        max_threshold: params.max_threshold_px.unwrap_or(f64::INFINITY),
        filter,
    };
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let reserve = ((params.max_iterations as f64 * params.reserve_fraction.clamp(0.0, 1.0)).round()
        as usize)
        .min(params.max_iterations);
    let all: Vec<usize> = (0..n).collect();
    let mut best = None;
    let mut iterations = sample_phase(
        &p,
        params,
        &all,
        0,
        params.max_iterations - reserve,
        &mut best,
    );

    // Resample from the best inlier set (IPOL's refinement reserve).
    if let Some(b) = best.as_ref().filter(|b| b.log10_nfa < 0.0 && b.k > m) {
        let pool = p.inliers(b);
        if pool.len() > m {
            iterations +=
                sample_phase(&p, params, &pool, params.max_iterations, reserve, &mut best);
        }
    }

    let mut buf = Vec::new();
    // Least-squares refits on the inliers while they lower the NFA.
    for _ in 0..3 {
        let Some(b) = best.as_ref() else { break };
        let pool = p.inliers(b);
        let refit = p
            .model
            .fit_least_squares(p.left, p.right, &pool)
            .and_then(|f| p.score(&f, &mut buf));
        match refit {
            Some(c) if c.log10_nfa < b.log10_nfa => best = Some(c),
            _ => break,
        }
    }

    match best {
        Some(b) if b.log10_nfa < 0.0 => Ok(OrsaResult {
            inliers: p.inliers(&b),
            f: b.f,
            log10_nfa: b.log10_nfa,
            threshold_px: b.threshold,
            iterations,
        }),
        Some(b) => Err(OrsaError::NotMeaningful {
            best_log10_nfa: b.log10_nfa,
            inliers: b.k,
        }),
        None => Err(OrsaError::NotMeaningful {
            best_log10_nfa: f64::INFINITY,
            inliers: 0,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::sparse::fundamental::tests::{affine_pair, projective_pair};
    use rand::Rng;

    /// `n_in` true matches with 0.3 px noise, then `n_out` random pairs.
    fn contaminate(
        (l, r): (Vec<Vector2<f64>>, Vec<Vector2<f64>>),
        n_out: usize,
        seed: u64,
    ) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut noise = || Vector2::new(rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3));
        let mut l: Vec<_> = l.into_iter().map(|p| p + noise()).collect();
        let mut r: Vec<_> = r.into_iter().map(|p| p + noise()).collect();
        for _ in 0..n_out {
            l.push(Vector2::new(
                rng.random_range(0.0..640.0),
                rng.random_range(0.0..480.0),
            ));
            r.push(Vector2::new(
                rng.random_range(0.0..640.0),
                rng.random_range(0.0..480.0),
            ));
        }
        (l, r)
    }

    #[test]
    fn finds_inliers_among_half_outliers() {
        for model in [FundamentalModel::Projective, FundamentalModel::Affine] {
            let data = if model == FundamentalModel::Projective {
                projective_pair(100, 4)
            } else {
                affine_pair(100, 4)
            };
            let (l, r) = contaminate(data, 100, 5);
            let params = OrsaParams {
                model,
                ..OrsaParams::default()
            };
            let res = orsa(&l, &r, [(640, 480); 2], &params).unwrap();
            let true_in = res.inliers.iter().filter(|&&i| i < 100).count();
            let false_in = res.inliers.len() - true_in;
            assert!(true_in >= 95, "{model:?}: {true_in} true inliers");
            // A random pair lies within ~1 px of an epipolar line by chance only rarely.
            assert!(false_in <= 4, "{model:?}: {false_in} outliers accepted");
            assert!(res.log10_nfa < -20.0, "{}", res.log10_nfa);
            assert!(
                res.threshold_px > 0.2 && res.threshold_px < 3.0,
                "{}",
                res.threshold_px
            );
        }
    }

    #[test]
    fn same_seed_same_result_other_seed_still_valid() {
        let (l, r) = contaminate(projective_pair(60, 7), 60, 8);
        let p = OrsaParams::default();
        let a = orsa(&l, &r, [(640, 480); 2], &p).unwrap();
        let b = orsa(&l, &r, [(640, 480); 2], &p).unwrap();
        assert_eq!(a, b);
        let c = orsa(&l, &r, [(640, 480); 2], &OrsaParams { seed: 99, ..p }).unwrap();
        assert!(c.inliers.iter().filter(|&&i| i < 60).count() >= 55);
    }

    #[test]
    fn pure_noise_is_not_meaningful() {
        let (l, r) = contaminate((Vec::new(), Vec::new()), 80, 11);
        let err = orsa(&l, &r, [(640, 480); 2], &OrsaParams::default()).unwrap_err();
        assert!(
            matches!(err, OrsaError::NotMeaningful { best_log10_nfa, .. } if best_log10_nfa >= 0.0),
            "{err}"
        );
        let err = orsa(&l[..5], &r[..5], [(640, 480); 2], &OrsaParams::default()).unwrap_err();
        assert_eq!(err, OrsaError::TooFewMatches { found: 5, need: 7 });
    }

    #[test]
    fn the_filter_decides_which_models_are_scored() {
        let (l, r) = contaminate(affine_pair(60, 4), 60, 12);
        let p = OrsaParams {
            model: FundamentalModel::Affine,
            ..OrsaParams::default()
        };
        let free = orsa(&l, &r, [(640, 480); 2], &p).unwrap();
        let all = |_: &Matrix3<f64>| true;
        let kept = orsa_filtered(&l, &r, [(640, 480); 2], &p, Some(&all)).unwrap();
        assert_eq!(kept, free);
        let none = |_: &Matrix3<f64>| false;
        let err = orsa_filtered(&l, &r, [(640, 480); 2], &p, Some(&none)).unwrap_err();
        assert!(
            matches!(err, OrsaError::NotMeaningful { inliers: 0, .. }),
            "{err}"
        );
    }
}
