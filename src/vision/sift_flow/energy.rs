//! The SIFT-flow energy, Liu, Yuen, Torralba (PAMI 2011) equation (10):
//!
//! ```text
//! E(w) = Σ_p min(‖s1(p) − s2(p + w(p))‖₁, t)                    data
//!      + Σ_p η (|u(p)| + |v(p)|)                                 small displacement
//!      + Σ_(p,q)∈ε min(α |u(p) − u(q)|, d) + min(α |v(p) − v(q)|, d)   smoothness
//! ```
//!
//! with `w = (u, v)` integer flow, `ε` the 4-neighbourhood. The reference code
//! calls η `gamma`; we keep that name. Each pixel's labels live in a window
//! `[−w, w]` around a per-pixel offset (coarse-to-fine initialisation), so the
//! flow is `offset + label − w`.

use rayon::prelude::*;

use crate::vision::dense_sift::{DescriptorImage, l1_distance};

/// Parameters of eq. (10) at one pyramid level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnergyWeights {
    /// α: slope of the truncated L1 smoothness.
    pub alpha: f32,
    /// d: truncation of the smoothness.
    pub d: f32,
    /// η (γ in the reference code): weight of the small-displacement term.
    pub gamma: f32,
}

/// Label geometry of one level: per-pixel offsets and uniform windows.
#[derive(Debug, Clone)]
pub struct LabelSpace {
    pub width: usize,
    pub height: usize,
    /// Per plane (0 = u, 1 = v): the half window `w`, states `2w + 1`.
    pub window: [usize; 2],
    /// Per plane: the offset of each pixel (row-major).
    pub offset: [Vec<i32>; 2],
}

impl LabelSpace {
    /// Number of states of plane `k`.
    #[must_use]
    pub fn states(&self, k: usize) -> usize {
        2 * self.window[k] + 1
    }

    /// The flow component of plane `k` at pixel `p` for label `l`.
    #[must_use]
    #[inline]
    pub fn flow(&self, k: usize, p: usize, l: usize) -> i32 {
        self.offset[k][p] + l as i32 - self.window[k] as i32
    }
}

/// The data term of eq. (10) for every pixel and label pair, `u16` per entry
/// (a descriptor L1 distance is at most 128 · 255 = 32 640).
///
/// Layout: `cost[(p · n_v + l_v) · n_u + l_u]`.
#[derive(Debug, Clone)]
pub struct DataTerm {
    pub cost: Vec<u16>,
    /// Cost given to matches that fall outside the second image (or on its
    /// invalid pixels): the median of the inside matches, as in the reference code.
    pub outside_cost: u16,
}

/// Marks a label whose match falls outside the second image during the first pass.
const OUTSIDE: u16 = u16::MAX;

impl DataTerm {
    /// Computes the data term of every label of `space`.
    ///
    /// `valid2` (row-major over `s2`) marks pixels of the second image that may
    /// be matched; `truncation` is `t` of eq. (10) (`None`: not truncated, as
    /// the reference code runs).
    #[must_use]
    pub fn compute(
        s1: &DescriptorImage,
        s2: &DescriptorImage,
        space: &LabelSpace,
        valid2: Option<&[bool]>,
        truncation: Option<f32>,
    ) -> Self {
        let (w, h) = (space.width, space.height);
        let (nu, nv) = (space.states(0), space.states(1));
        let (w2, h2) = (s2.width() as i64, s2.height() as i64);
        let per_pixel = nu * nv;
        let mut cost = vec![0u16; w * h * per_pixel];
        cost.par_chunks_mut(w * per_pixel)
            .enumerate()
            .for_each(|(y, row)| {
                for x in 0..w {
                    let p = y * w + x;
                    let a = s1.at(x, y);
                    let out = &mut row[x * per_pixel..(x + 1) * per_pixel];
                    for lv in 0..nv {
                        let y2 = y as i64 + i64::from(space.flow(1, p, lv));
                        for lu in 0..nu {
                            let x2 = x as i64 + i64::from(space.flow(0, p, lu));
                            let inside = x2 >= 0 && x2 < w2 && y2 >= 0 && y2 < h2;
                            out[lv * nu + lu] = if !inside {
                                OUTSIDE
                            } else {
                                // Inside the image: the casts are in range.
                                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                                let (xx, yy) = (x2 as usize, y2 as usize);
                                if valid2.is_some_and(|m| !m[yy * s2.width() + xx]) {
                                    OUTSIDE
                                } else {
                                    // At most 32 640: fits.
                                    #[allow(clippy::cast_possible_truncation)]
                                    let c = l1_distance(a, s2.at(xx, yy)) as u16;
                                    c
                                }
                            };
                        }
                    }
                }
            });
        let outside_cost = median_inside(&cost);
        let cap = truncation.map_or(u16::MAX - 1, |t| {
            // Clamped into the u16 range first.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let c = t.clamp(0.0, f32::from(u16::MAX - 1)) as u16;
            c
        });
        cost.par_iter_mut().for_each(|c| {
            *c = if *c == OUTSIDE {
                outside_cost.min(cap)
            } else {
                (*c).min(cap)
            };
        });
        Self { cost, outside_cost }
    }

    /// The costs of pixel `p`, `[l_v][l_u]`.
    #[must_use]
    #[inline]
    pub fn pixel(&self, p: usize, per_pixel: usize) -> &[u16] {
        &self.cost[p * per_pixel..(p + 1) * per_pixel]
    }
}

/// The median of the entries that are not [`OUTSIDE`] (a histogram over u16);
/// 0 when every match falls outside.
fn median_inside(cost: &[u16]) -> u16 {
    let hist = cost
        .par_chunks(1 << 16)
        .fold(
            || vec![0u64; 1 << 15],
            |mut h, chunk| {
                for &c in chunk {
                    if c != OUTSIDE {
                        h[usize::from(c >> 1)] += 1;
                    }
                }
                h
            },
        )
        .reduce(
            || vec![0u64; 1 << 15],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        );
    let total: u64 = hist.iter().sum();
    let mut acc = 0;
    for (i, &n) in hist.iter().enumerate() {
        acc += n;
        if 2 * acc >= total && total > 0 {
            // i < 2^15, so 2i + 1 fits in u16.
            #[allow(clippy::cast_possible_truncation)]
            return (2 * i + 1) as u16;
        }
    }
    0
}

/// Energy (10) of a labelling (`labels[k][p]`), summed in f64.
#[must_use]
pub fn energy(
    data: &DataTerm,
    space: &LabelSpace,
    labels: &[Vec<u16>; 2],
    weights: &EnergyWeights,
) -> f64 {
    let (w, h) = (space.width, space.height);
    let (nu, nv) = (space.states(0), space.states(1));
    (0..h)
        .into_par_iter()
        .map(|y| {
            let mut e = 0f64;
            for x in 0..w {
                let p = y * w + x;
                let (lu, lv) = (usize::from(labels[0][p]), usize::from(labels[1][p]));
                e += f64::from(data.cost[p * nu * nv + lv * nu + lu]);
                for k in 0..2 {
                    let f = space.flow(k, p, usize::from(labels[k][p]));
                    e += f64::from(weights.gamma) * f64::from(f.abs());
                    let pair = |q: usize| {
                        let g = space.flow(k, q, usize::from(labels[k][q]));
                        #[allow(clippy::cast_precision_loss)]
                        let diff = (f - g).unsigned_abs() as f32;
                        f64::from((weights.alpha * diff).min(weights.d))
                    };
                    if x + 1 < w {
                        e += pair(p + 1);
                    }
                    if y + 1 < h {
                        e += pair(p + w);
                    }
                }
            }
            e
        })
        .sum()
}
