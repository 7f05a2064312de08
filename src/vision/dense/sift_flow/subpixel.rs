//! Sub-pixel flow from the labels of BP (beyond the paper, whose SIFT flow
//! is integer).
//!
//! Around the chosen label `l*` of one layer, the data term of eq. (10) at
//! `l* − 1, l*, l* + 1` (the other layer held at its label) is fitted by a
//! symmetric "V" — the equiangular fit of Shimizu & Okutomi, the right model
//! for an L1 cost (a sum of absolute differences grows linearly with a small
//! shift) where a parabola pulls estimates towards the integers. The minimum
//! of the V moves the label by
//! `δ = (c₋ − c₊) / (2 · max(c₋ − c₀, c₊ − c₀))`, limited to ±0.5.

use rayon::prelude::*;

use super::energy::{DataTerm, LabelSpace};

/// Minimum of the V through `(−1, cm)`, `(0, c0)`, `(1, cp)`; 0 when `c0`
/// is not the smallest (a plateau or an edge of the window).
#[must_use]
#[inline]
pub fn equiangular_offset(cm: f32, c0: f32, cp: f32) -> f32 {
    let slope = (cm - c0).max(cp - c0);
    if slope <= 0.0 || c0 > cm || c0 > cp {
        return 0.0;
    }
    ((cm - cp) / (2.0 * slope)).clamp(-0.5, 0.5)
}

/// The flow of both layers with sub-pixel precision: integer flow of the
/// labels plus the equiangular offset on the data term.
#[must_use]
pub fn refine(data: &DataTerm, space: &LabelSpace, labels: &[Vec<u16>; 2]) -> [Vec<f32>; 2] {
    let (nu, nv) = (space.states(0), space.states(1));
    let area = space.width * space.height;
    let layer = |k: usize| -> Vec<f32> {
        (0..area)
            .into_par_iter()
            .map(|p| {
                let c = data.pixel(p, nu * nv);
                let (lu, lv) = (usize::from(labels[0][p]), usize::from(labels[1][p]));
                let at = |u: usize, v: usize| f32::from(c[v * nu + u]);
                let delta = if k == 0 {
                    if lu == 0 || lu + 1 >= nu {
                        0.0
                    } else {
                        equiangular_offset(at(lu - 1, lv), at(lu, lv), at(lu + 1, lv))
                    }
                } else if lv == 0 || lv + 1 >= nv {
                    0.0
                } else {
                    equiangular_offset(at(lu, lv - 1), at(lu, lv), at(lu, lv + 1))
                };
                space.flow(k, p, usize::from(labels[k][p])) as f32 + delta
            })
            .collect()
    };
    [layer(0), layer(1)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equiangular_fit_recovers_the_apex_of_a_v() {
        for &apex in &[-0.4f32, -0.1, 0.0, 0.25, 0.49] {
            let v = |x: f32| 3.0 * (x - apex).abs() + 1.0;
            let got = equiangular_offset(v(-1.0), v(0.0), v(1.0));
            assert!((got - apex).abs() < 1e-5, "apex {apex}: {got}");
        }
        // Not a minimum in the middle: no refinement.
        assert_eq!(equiangular_offset(1.0, 2.0, 3.0), 0.0);
        assert_eq!(equiangular_offset(2.0, 2.0, 2.0), 0.0);
    }
}
