//! Descriptor matching: nearest neighbour with Lowe's ratio test and a symmetric
//! (mutual nearest neighbour) check (Lowe 2004 §7.1).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::sparse::sift::{DESCRIPTOR_LEN, Keypoint};

/// Parameters of descriptor matching.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatchParams {
    /// Lowe's ratio: a match is kept when `d(nearest) < ratio · d(second nearest)` (Euclidean
    /// distances; default 0.8 as in Lowe 2004 §7.1). Lower: fewer, surer matches.
    pub ratio: f64,
    /// Keep only mutual nearest neighbours: the left keypoint is also the nearest to its right
    /// partner (default true). Removes most many-to-one matches on repetitive texture.
    pub symmetric: bool,
}

impl Default for MatchParams {
    fn default() -> Self {
        Self {
            ratio: 0.8,
            symmetric: true,
        }
    }
}

/// A putative correspondence: indices into the left and right keypoint lists.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Match {
    pub left: usize,
    pub right: usize,
    /// Euclidean descriptor distance of the match.
    pub distance: f32,
    /// Distance to the nearest divided by distance to the second nearest (≤ ratio).
    pub ratio: f32,
}

/// A descriptor widened to `i16`: differences then fit, and the squared distance compiles to
/// multiply-add of 16-bit pairs (SSE2 `pmaddwd`), ~2.5× faster than on bytes.
type Wide = [i16; DESCRIPTOR_LEN];

/// Squared Euclidean distance of two descriptors (exact, in integers).
#[inline]
#[must_use]
fn distance2(a: &Wide, b: &Wide) -> u32 {
    // Wrapping arithmetic: it cannot wrap here (|d| ≤ 255, sum ≤ 128·255²), and unlike checked
    // arithmetic (debug and test builds) it leaves the loop free to vectorise.
    let s: i32 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = i32::from(x.wrapping_sub(y));
            d.wrapping_mul(d)
        })
        .fold(0, i32::wrapping_add);
    s.unsigned_abs()
}

/// For each left descriptor, the nearest and second-nearest right ones; for each right
/// descriptor, the nearest left one. One pass over all pairs, parallel over left blocks;
/// ties go to the smaller index, so the result does not depend on the thread count.
struct Neighbours {
    /// (best index, best d², second d²) per left descriptor.
    left: Vec<(usize, u32, u32)>,
    /// (best index, best d²) per right descriptor.
    right: Vec<(usize, u32)>,
}

const BLOCK: usize = 64;

/// Per block of left descriptors: their (best, d², second d²) and every right one's (best, d²).
type BlockResult = (Vec<(usize, u32, u32)>, Vec<(usize, u32)>);

fn neighbours(left: &[Wide], right: &[Wide]) -> Neighbours {
    let n_right = right.len();
    let blocks: Vec<BlockResult> = left
        .par_chunks(BLOCK)
        .enumerate()
        .map(|(b, chunk)| {
            let mut lbest = vec![(usize::MAX, u32::MAX, u32::MAX); chunk.len()];
            let mut rbest = vec![(usize::MAX, u32::MAX); n_right];
            for (j, r) in right.iter().enumerate() {
                for (k, l) in chunk.iter().enumerate() {
                    let d = distance2(l, r);
                    let e = &mut lbest[k];
                    if d < e.1 {
                        *e = (j, d, e.1);
                    } else if d < e.2 {
                        e.2 = d;
                    }
                    let i = b * BLOCK + k;
                    if d < rbest[j].1 {
                        rbest[j] = (i, d);
                    }
                }
            }
            (lbest, rbest)
        })
        .collect();
    let mut left_out = Vec::with_capacity(left.len());
    let mut right_out = vec![(usize::MAX, u32::MAX); n_right];
    for (lb, rb) in blocks {
        left_out.extend(lb);
        for (acc, cand) in right_out.iter_mut().zip(rb) {
            // Blocks arrive in index order: strict `<` keeps the smaller index on ties.
            if cand.1 < acc.1 {
                *acc = cand;
            }
        }
    }
    Neighbours {
        left: left_out,
        right: right_out,
    }
}

/// Matches `left` keypoints to `right` ones.
///
/// A left keypoint is matched to its nearest right neighbour when the ratio test passes
/// and, with `params.symmetric`, when it is also that neighbour's nearest left keypoint.
/// The result is sorted by left index.
#[must_use]
pub fn match_keypoints(left: &[Keypoint], right: &[Keypoint], params: &MatchParams) -> Vec<Match> {
    if left.is_empty() || right.len() < 2 {
        return Vec::new();
    }
    let ld: Vec<Wide> = left.iter().map(|k| k.descriptor.map(i16::from)).collect();
    let rd: Vec<Wide> = right.iter().map(|k| k.descriptor.map(i16::from)).collect();
    let nn = neighbours(&ld, &rd);
    let ratio2 = params.ratio * params.ratio;
    nn.left
        .iter()
        .enumerate()
        .filter_map(|(i, &(j, d1, d2))| {
            let (d1f, d2f) = (f64::from(d1), f64::from(d2));
            if d1f >= ratio2 * d2f {
                return None;
            }
            if params.symmetric && nn.right[j].0 != i {
                return None;
            }
            #[allow(clippy::cast_possible_truncation)]
            Some(Match {
                left: i,
                right: j,
                distance: d1f.sqrt() as f32,
                ratio: if d2 == 0 {
                    1.0
                } else {
                    (d1f / d2f).sqrt() as f32
                },
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(desc: [u8; DESCRIPTOR_LEN]) -> Keypoint {
        Keypoint {
            x: 0.0,
            y: 0.0,
            sigma: 1.0,
            theta: 0.0,
            response: 0.1,
            descriptor: desc,
        }
    }

    fn desc(seed: u64) -> [u8; DESCRIPTOR_LEN] {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        std::array::from_fn(|_| rng.random_range(0..=255u8))
    }

    /// Brute force, written plainly: the reference for the blocked parallel search.
    fn naive(left: &[Keypoint], right: &[Keypoint], p: &MatchParams) -> Vec<(usize, usize)> {
        let d = |a: &Keypoint, b: &Keypoint| -> f64 {
            a.descriptor
                .iter()
                .zip(&b.descriptor)
                .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let mut out = Vec::new();
        for (i, l) in left.iter().enumerate() {
            let mut ds: Vec<(f64, usize)> = right
                .iter()
                .enumerate()
                .map(|(j, r)| (d(l, r), j))
                .collect();
            ds.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            if ds[0].0 >= p.ratio * ds[1].0 {
                continue;
            }
            let j = ds[0].1;
            let back = left
                .iter()
                .enumerate()
                .map(|(k, l2)| (d(l2, &right[j]), k))
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                .unwrap()
                .1;
            if !p.symmetric || back == i {
                out.push((i, j));
            }
        }
        out
    }

    #[test]
    fn agrees_with_brute_force() {
        // Right = noisy copies of some left descriptors plus distractors; more than one block.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let left: Vec<_> = (0..150).map(|s| kp(desc(s))).collect();
        let mut right: Vec<_> = (0..100)
            .map(|s| {
                let mut d = desc(s);
                for v in &mut d {
                    *v = v.saturating_add(rng.random_range(0..40));
                }
                kp(d)
            })
            .collect();
        right.extend((1000..1080).map(|s| kp(desc(s))));
        for p in [
            MatchParams::default(),
            MatchParams {
                ratio: 0.95,
                symmetric: false,
            },
        ] {
            let fast: Vec<_> = match_keypoints(&left, &right, &p)
                .iter()
                .map(|m| (m.left, m.right))
                .collect();
            assert_eq!(fast, naive(&left, &right, &p));
        }
        let m = match_keypoints(&left, &right, &MatchParams::default());
        assert!(
            m.len() >= 95 && m.iter().all(|m| m.left == m.right),
            "{}",
            m.len()
        );
    }

    #[test]
    fn ambiguous_descriptor_fails_ratio_test() {
        let a = desc(1);
        let left = vec![kp(a)];
        let right = vec![kp(a), kp(a), kp(desc(2))];
        assert!(match_keypoints(&left, &right, &MatchParams::default()).is_empty());
    }
}

#[cfg(test)]
mod bench {
    use super::*;
    #[test]
    #[ignore = "timing"]
    fn time_2000() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mk = |rng: &mut rand_chacha::ChaCha8Rng| Keypoint {
            x: 0.0,
            y: 0.0,
            sigma: 1.0,
            theta: 0.0,
            response: 0.0,
            descriptor: std::array::from_fn(|_| rng.random_range(0..=255u8)),
        };
        let l: Vec<_> = (0..2000).map(|_| mk(&mut rng)).collect();
        let r: Vec<_> = (0..2000).map(|_| mk(&mut rng)).collect();
        for _ in 0..3 {
            let t = std::time::Instant::now();
            let m = match_keypoints(&l, &r, &MatchParams::default());
            println!("{:?} {}", t.elapsed(), m.len());
        }
    }
}
