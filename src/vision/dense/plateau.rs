//! Plateaus measured apart from their outline (beyond the paper; opt-in, `slanted.plateau`).
//!
//! A raised, nearly featureless plateau with walls steeper than half the tilt (the bars of a
//! calibration grid) shows each view a wall the other does not: its bright outline, the
//! strongest texture, moves by about half the top's parallax, and a window that straddles it
//! measures the top at about half its height. Here the bright, flat pixels of the left canvas
//! (above the midpoint of its brightness range, gradient below `plateau_max_gradient` of that
//! range, one pixel in from the rest) form plateaus (connected, at least `plateau_min_px`);
//! each is matched again with box windows restricted to it, so the outline does not enter:
//! zero-mean NCC at every integer disparity within `plateau_reach` of the field's range over
//! the plateau, a parabola through the best three. A pixel takes the new disparity when its
//! peak reaches `plateau_min_ncc`, and a plateau only when the median of its new disparities
//! differs from the matcher's by `plateau_min_shift_px`: on textured scenes bright, flat
//! patches abound, the matcher measured them, and the box windows would only add their own
//! error (fronto-parallel over 33 pixels) and cost.

use rayon::prelude::*;

use super::slanted::SlantedParams;
use super::support::Unknown;
use crate::vision::Image;
use crate::vision::filter::blur::gaussian_blur;

/// The bright, flat pixels of `a` (valid ones only), eroded by one pixel; the bright ones; the
/// dark, flat ones, eroded alike.
#[must_use]
pub fn plateau_mask(a: &Image, va: &[bool], max_gradient: f32) -> [Vec<bool>; 3] {
    let (w, h) = a.dimensions();
    let key = gaussian_blur(a, 1.0);
    let k = key.data();
    let mut vals: Vec<f32> = k
        .iter()
        .zip(va)
        .filter(|(_, v)| **v)
        .map(|(x, _)| *x)
        .collect();
    if vals.len() < 16 || w < 3 || h < 3 {
        return [vec![false; w * h], vec![false; w * h], vec![false; w * h]];
    }
    // The 10th and 99th percentiles, as a sort would give them, by two selections.
    let at = |q: f64| ((vals.len() - 1) as f64 * q) as usize;
    let (i, j) = (at(0.10), at(0.99));
    let lo = *vals.select_nth_unstable_by(i, f32::total_cmp).1;
    let hi = if j > i {
        *vals[i + 1..]
            .select_nth_unstable_by(j - i - 1, f32::total_cmp)
            .1
    } else {
        lo
    };
    let (mid, gmax) = (0.5 * (lo + hi), max_gradient * (hi - lo));
    let bright: Vec<bool> = k.iter().zip(va).map(|(k, v)| *v && *k > mid).collect();
    let flat = |up: bool| -> Vec<bool> {
        (0..w * h)
            .into_par_iter()
            .map(|p| {
                let (x, y) = (p % w, p / w);
                if !va[p] || (k[p] > mid) != up || x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    return false;
                }
                let gx = 0.5 * (k[p + 1] - k[p - 1]);
                let gy = 0.5 * (k[p + w] - k[p - w]);
                gx.hypot(gy) < gmax
            })
            .collect()
    };
    // One pixel in: the mask's own rim lies on the outline's shoulder.
    let eroded = |flat: Vec<bool>| -> Vec<bool> {
        (0..w * h)
            .into_par_iter()
            .map(|p| {
                let (x, y) = (p % w, p / w);
                flat[p]
                    && (y.saturating_sub(1)..(y + 2).min(h))
                        .all(|j| (x.saturating_sub(1)..(x + 2).min(w)).all(|i| flat[j * w + i]))
            })
            .collect()
    };
    [eroded(flat(true)), bright, eroded(flat(false))]
}

/// Sums over the `(2r+1)²` box around each pixel (clipped at the borders).
fn box_sum(src: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let mut rows = vec![0.0; w * h];
    rows.par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(out, row)| {
            let mut prefix = vec![0.0; w + 1];
            for (i, v) in row.iter().enumerate() {
                prefix[i + 1] = prefix[i] + v;
            }
            for (x, o) in out.iter_mut().enumerate() {
                *o = prefix[(x + r + 1).min(w)] - prefix[x.saturating_sub(r)];
            }
        });
    let mut out = vec![0.0; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, o)| {
        for j in y.saturating_sub(r)..(y + r + 1).min(h) {
            for (a, b) in o.iter_mut().zip(&rows[j * w..(j + 1) * w]) {
                *a += b;
            }
        }
    });
    out
}

/// No candidate has a finite score yet.
const NONE: u32 = u32::MAX;

/// A plateau pixel's best candidate so far: its index `k` ([`NONE`] before any), its score and
/// the scores of the candidates either side (NaN until seen).
#[derive(Debug, Clone, Copy)]
struct Best {
    k: u32,
    zm: f32,
    z0: f32,
    zp: f32,
}

/// Rows of output per task of [`best_matches`]: each task sums `2 r` more rows than it answers
/// for, so taller blocks waste less; 64 keeps a task's sums within a few MiB.
const BLOCK_ROWS: usize = 64;

/// For each pixel of `mask`, the best of the integer disparities `first..=last` by zero-mean NCC
/// over the masked `(2r+1)²` box (the right pixel valid and inside the canvas), and its
/// neighbours' scores. The six sums (count, Σa, Σb, Σa², Σb², Σab) are built in one pass per
/// candidate, block of rows by block of rows, and only a running best is kept: memory is a few
/// rows' sums per task, not a plane per candidate. The arithmetic per sum is that of a row
/// prefix then a column sum in ascending rows, so the scores do not depend on the blocks.
/// Returns the first row with a mask pixel and the results from that row to the last one's.
fn best_matches(
    (a, b): (&Image, &Image),
    vb: &[bool],
    mask: &[bool],
    (first, last): (i64, i64),
    r: usize,
) -> (usize, Vec<Best>) {
    let (w, h) = a.dimensions();
    let (ad, bd) = (a.data(), b.data());
    let unset = Best {
        k: NONE,
        zm: f32::NAN,
        z0: f32::NAN,
        zp: f32::NAN,
    };
    // The masked columns of each row, `[lo, hi)` (empty: none).
    let spans: Vec<(usize, usize)> = mask
        .par_chunks(w.max(1))
        .map(|row| {
            let lo = row.iter().position(|m| *m).unwrap_or(w);
            let hi = row.iter().rposition(|m| *m).map_or(0, |x| x + 1);
            (lo, hi.max(lo))
        })
        .collect();
    let Some(ya) = spans.iter().position(|(lo, hi)| lo < hi) else {
        return (0, Vec::new());
    };
    let yb = spans
        .iter()
        .rposition(|(lo, hi)| lo < hi)
        .map_or(ya, |y| y + 1);
    let mut best = vec![unset; (yb - ya) * w];
    best.par_chunks_mut(BLOCK_ROWS * w.max(1))
        .enumerate()
        .for_each(|(block, out)| {
            let y0 = ya + block * BLOCK_ROWS;
            let y1 = (y0 + BLOCK_ROWS).min(yb);
            if spans[y0..y1].iter().all(|(lo, hi)| lo >= hi) {
                return;
            }
            // Rows whose sums reach the block's; a row without mask pixels sums to +0 and
            // adding +0 changes no sum, so it is left out.
            let (s0, s1) = (y0.saturating_sub(r), (y1 + r).min(h));
            let rows: Vec<usize> = (s0..s1).filter(|&j| spans[j].0 < spans[j].1).collect();
            let mut sums = vec![[0.0f64; 6]; rows.len() * w];
            let mut prefix = vec![[0.0f64; 6]; w + 1];
            let mut col = vec![[0.0f64; 6]; w];
            let mut prev = vec![f32::NAN; (y1 - y0) * w];
            for (k, d) in (first..=last).enumerate() {
                // Row sums over the box's width: a prefix along the row, then differences.
                for (i, &j) in rows.iter().enumerate() {
                    for x in 0..w {
                        let p = j * w + x;
                        let xr = x as i64 + d;
                        let t =
                            if mask[p] && xr >= 0 && xr < w as i64 && vb[(p as i64 + d) as usize] {
                                let (u, v) =
                                    (f64::from(ad[p]), f64::from(bd[(p as i64 + d) as usize]));
                                [1.0, u, v, u * u, v * v, u * v]
                            } else {
                                [0.0; 6]
                            };
                        for c in 0..6 {
                            prefix[x + 1][c] = prefix[x][c] + t[c];
                        }
                    }
                    let row = &mut sums[i * w..(i + 1) * w];
                    for (x, o) in row.iter_mut().enumerate() {
                        let (hi, lo) = (&prefix[(x + r + 1).min(w)], &prefix[x.saturating_sub(r)]);
                        for c in 0..6 {
                            o[c] = hi[c] - lo[c];
                        }
                    }
                }
                for (y, &(lo, hi)) in spans.iter().enumerate().take(y1).skip(y0) {
                    if lo >= hi {
                        continue;
                    }
                    let (j0, j1) = (y.saturating_sub(r), (y + r + 1).min(h));
                    let cols = &mut col[lo..hi];
                    cols.fill([0.0; 6]);
                    for (i, _) in rows
                        .iter()
                        .enumerate()
                        .filter(|(_, j)| (j0..j1).contains(*j))
                    {
                        for (o, s) in cols.iter_mut().zip(&sums[i * w + lo..i * w + hi]) {
                            for c in 0..6 {
                                o[c] += s[c];
                            }
                        }
                    }
                    for (x, s) in (lo..hi).zip(cols.iter()) {
                        let p = y * w + x;
                        if !mask[p] {
                            continue;
                        }
                        let z = ncc(s);
                        let i = p - y0 * w;
                        let m = &mut out[i];
                        if m.k != NONE && m.k as usize + 1 == k {
                            m.zp = z;
                        }
                        if z.is_finite() && (m.k == NONE || m.z0.total_cmp(&z).is_le()) {
                            *m = Best {
                                k: k as u32,
                                zm: prev[i],
                                z0: z,
                                zp: f32::NAN,
                            };
                        }
                        prev[i] = z;
                    }
                }
            }
        });
    (ya, best)
}

/// Zero-mean NCC from the sums (count, Σa, Σb, Σa², Σb², Σab); NaN below 4 samples or
/// without variance.
fn ncc(s: &[f64; 6]) -> f32 {
    let [n, sa, sb, saa, sbb, sab] = *s;
    if n < 4.0 {
        return f32::NAN;
    }
    let (ma, mb) = (sa / n, sb / n);
    let vaa = saa / n - ma * ma;
    let vbb = sbb / n - mb * mb;
    let cab = sab / n - ma * mb;
    let den = (vaa * vbb).sqrt();
    if den > 0.0 {
        (cab / den) as f32
    } else {
        f32::NAN
    }
}

/// The connected (8-neighbour) regions of `mask` of at least `min_px` pixels, each as a mask.
fn plateaus(mask: &[bool], (w, h): (usize, usize), min_px: usize) -> Vec<Vec<bool>> {
    let mut seen = vec![false; w * h];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut region = Vec::new();
        while let Some(p) = stack.pop() {
            region.push(p);
            let (x, y) = (p % w, p / w);
            for j in y.saturating_sub(1)..(y + 2).min(h) {
                for i in x.saturating_sub(1)..(x + 2).min(w) {
                    let q = j * w + i;
                    if mask[q] && !seen[q] {
                        seen[q] = true;
                        stack.push(q);
                    }
                }
            }
        }
        if region.len() >= min_px.max(1) {
            let mut own = vec![false; w * h];
            for p in region {
                own[p] = true;
            }
            out.push(own);
        }
    }
    out
}

/// One plateau's new disparities (pixel, disparity, NCC at the best integer): the candidates
/// span the matcher's range over it and `plateau_reach` beyond, a parabola through the best
/// three refines the best, and a pixel whose best is at the range's end or below
/// `plateau_min_ncc` keeps the matcher's.
fn measure_plateau(
    (a, b): (&Image, &Image),
    vb: &[bool],
    own: &[bool],
    raw: &[f32],
    q: &SlantedParams,
) -> Vec<(usize, f32, f32)> {
    let (lo, hi) = raw
        .iter()
        .zip(own)
        .filter(|(d, m)| **m && d.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, u), (d, _)| {
            (l.min(*d), u.max(*d))
        });
    if !lo.is_finite() {
        return Vec::new();
    }
    let first = (lo - q.plateau_reach).floor() as i64;
    let last = (hi + q.plateau_reach).ceil() as i64;
    let (y0, best) = best_matches((a, b), vb, own, (first, last), q.plateau_radius);
    let w = a.width();
    let top = (last - first) as usize;
    best.iter()
        .enumerate()
        .filter_map(|(i, m)| {
            let p = y0 * w + i;
            if !own[p] || m.k == NONE {
                return None;
            }
            let k = m.k as usize;
            if k == 0 || k == top || m.z0 < q.plateau_min_ncc {
                return None;
            }
            let (zm, z0, zp) = (m.zm, m.z0, m.zp);
            let den = zm - 2.0 * z0 + zp;
            let off = if den < 0.0 && den.is_finite() {
                (0.5 * (zm - zp) / den).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            Some((p, (first + k as i64) as f32 + off, z0))
        })
        .collect()
}

/// Re-measures the plateau pixels of `raw` (see the module's comment); returns how many took a
/// new disparity.
pub fn measure_plateaus(
    (a, b): (&Image, &Image),
    (va, vb): (&[bool], &[bool]),
    (raw, confidence, unknown): (&mut Image, &mut Image, &mut [Unknown]),
    q: &SlantedParams,
) -> usize {
    let (w, h) = a.dimensions();
    let [mask, bright, dark] = plateau_mask(a, va, q.plateau_max_gradient);
    let mut changed = 0;
    let mut took = vec![false; w * h];
    for own in plateaus(&mask, (w, h), q.plateau_min_px) {
        let taken = measure_plateau((a, b), vb, &own, raw.data(), q);
        // Where the matcher already agrees with the restricted windows, it measured the top.
        let mut shifts: Vec<f32> = taken
            .iter()
            .map(|&(p, d, _)| d - raw.data()[p])
            .filter(|s| s.is_finite())
            .collect();
        if shifts.is_empty() {
            continue;
        }
        let mid = shifts.len() / 2;
        let (_, shift, _) = shifts.select_nth_unstable_by(mid, f32::total_cmp);
        if shift.abs() < q.plateau_min_shift_px {
            continue;
        }
        let (rd, cd) = (raw.data_mut(), confidence.data_mut());
        for (p, d, z0) in taken {
            rd[p] = d;
            // Not below the matcher's: the weighted filter must not let the outline's pixels win.
            cd[p] = cd[p].max(z0.clamp(0.0, 1.0));
            unknown[p] = Unknown::Measured;
            took[p] = true;
            changed += 1;
        }
    }
    let (rd, cd) = (raw.data_mut(), confidence.data_mut());
    // The bright rim around a plateau belongs to the raised surface: it takes the mean of the
    // plateau's new disparities within plateau_rim_px (the outline's own match is half-way).
    let s = q.plateau_rim_px;
    if s > 0 && changed > 0 {
        let vals: Vec<f64> = (0..w * h)
            .map(|p| if took[p] { f64::from(rd[p]) } else { 0.0 })
            .collect();
        let ones: Vec<f64> = took.iter().map(|t| f64::from(u8::from(*t))).collect();
        let (sum, n) = (box_sum(&vals, w, h, s), box_sum(&ones, w, h, s));
        for p in (0..w * h).filter(|&p| bright[p] && !mask[p] && n[p] > 0.0) {
            rd[p] = (sum[p] / n[p]) as f32;
            unknown[p] = Unknown::Measured;
            cd[p] = cd[p].max(0.5);
        }
    }
    // The dark, flat support between plateaus: its own texture is the scan noise and each wall's
    // foot is seen by one view only, so nothing in the micrographs tells its disparity.
    if q.plateau_floor_unknown && changed > 0 {
        for p in (0..w * h).filter(|&p| dark[p]) {
            rd[p] = f32::NAN;
            cd[p] = 0.0;
            unknown[p] = Unknown::NoTexture;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bright bar whose outline moves by half the top's parallax, its top carrying a faint
    /// texture that moves by all of it, on a dark, featureless floor.
    fn bar_pair(w: usize, h: usize, top: f32) -> (Image, Image) {
        let texture = |x: f32, y: f32| 0.03 * ((0.9 * x).sin() * (0.7 * y).cos());
        // Left: bar over [30, 62); right: outline shifted by top/2, top texture by top.
        let render = |outline: f32, shift: f32| {
            let mut v = vec![0.1f32; w * h];
            for y in 0..h {
                for x in 0..w {
                    let xf = x as f32;
                    if xf >= 30.0 - outline && xf < 62.0 - outline {
                        v[y * w + x] = 0.7 + texture(xf + shift, y as f32);
                    }
                }
            }
            Image::from_vec(w, h, v).unwrap()
        };
        (render(0.0, 0.0), render(top / 2.0, top))
    }

    /// The scores as the pass first computed them: six box-summed planes and one score plane
    /// per candidate, the best by `max_by` (the last of equal ones).
    fn reference_best(
        (a, b): (&Image, &Image),
        vb: &[bool],
        mask: &[bool],
        (first, last): (i64, i64),
        r: usize,
    ) -> Vec<Option<(usize, [f32; 3])>> {
        let (w, h) = a.dimensions();
        let (ad, bd) = (a.data(), b.data());
        let scores: Vec<Vec<f32>> = (first..=last)
            .map(|d| {
                let sample = |p: usize| {
                    let x = (p % w) as i64 + d;
                    let q = p as i64 + d;
                    (mask[p] && x >= 0 && x < w as i64 && vb[q as usize])
                        .then(|| (f64::from(ad[p]), f64::from(bd[q as usize])))
                };
                let terms = |f: fn(f64, f64) -> f64| {
                    let v: Vec<f64> = (0..w * h)
                        .map(|p| sample(p).map_or(0.0, |(x, y)| f(x, y)))
                        .collect();
                    box_sum(&v, w, h, r)
                };
                let planes = [
                    terms(|_, _| 1.0),
                    terms(|x, _| x),
                    terms(|_, y| y),
                    terms(|x, _| x * x),
                    terms(|_, y| y * y),
                    terms(|x, y| x * y),
                ];
                (0..w * h)
                    .map(|p| ncc(&std::array::from_fn(|c| planes[c][p])))
                    .collect()
            })
            .collect();
        (0..w * h)
            .map(|p| {
                let z = |k: usize| scores[k][p];
                let k = (0..scores.len())
                    .filter(|&k| z(k).is_finite())
                    .max_by(|&i, &j| z(i).total_cmp(&z(j)))?;
                let at = |k: Option<usize>| k.filter(|&k| k < scores.len()).map_or(f32::NAN, z);
                Some((k, [at(k.checked_sub(1)), z(k), at(Some(k + 1))]))
            })
            .collect()
    }

    /// The blocked, running search finds bit for bit the candidate and scores the planes of
    /// every candidate give: masks with empty rows and blocks, invalid right pixels, windows
    /// across block borders and the canvas's, equal scores (a constant-shift pair).
    #[test]
    fn the_running_search_matches_the_per_candidate_planes() {
        let (w, h) = (83usize, 150usize);
        let noise = |x: usize, y: usize, s: u64| {
            let mut v = (x as u64 * 73_856_093) ^ (y as u64 * 19_349_663) ^ s;
            v ^= v >> 13;
            v = v.wrapping_mul(0x5bd1_e995);
            v ^= v >> 15;
            (v % 1000) as f32 / 1000.0
        };
        let a = Image::from_fn(w, h, |x, y| noise(x, y, 1));
        let b = Image::from_fn(w, h, |x, y| 0.5 * noise(x + 3, y, 1) + 0.2 * noise(x, y, 2));
        let vb: Vec<bool> = (0..w * h).map(|p| p % 17 != 0).collect();
        // Two patches in different blocks, rows 70..75 empty, a thin line in between.
        let mask: Vec<bool> = (0..w * h)
            .map(|p| {
                let (x, y) = (p % w, p / w);
                (y < 70 && x > 5 && x < 60 && (x + y) % 5 != 0)
                    || (y == 76 && x < 40)
                    || (y > 100 && x > 30)
            })
            .collect();
        for (r, range) in [(4, (-6, 2)), (16, (-5, 5)), (1, (0, 0))] {
            let (y0, got) = best_matches((&a, &b), &vb, &mask, range, r);
            let want = reference_best((&a, &b), &vb, &mask, range, r);
            let mut found = 0;
            for p in (0..w * h).filter(|&p| mask[p]) {
                let g = got[p - y0 * w];
                let g = (g.k != NONE).then_some((g.k as usize, [g.zm, g.z0, g.zp]));
                let bits = |v: Option<(usize, [f32; 3])>| v.map(|(k, z)| (k, z.map(f32::to_bits)));
                assert_eq!(bits(g), bits(want[p]), "r {r}, pixel {p}");
                found += usize::from(g.is_some());
            }
            assert!(found > 1000, "{found}");
        }
        // Equal scores everywhere: the last candidate wins, as `max_by` has it.
        let flat = Image::from_fn(w, h, |x, _| (x % 7) as f32);
        let shifted = Image::from_fn(w, h, |x, _| (x % 7) as f32);
        let all = vec![true; w * h];
        let (_, got) = best_matches((&flat, &shifted), &all, &all, (-7, 7), 3);
        let want = reference_best((&flat, &shifted), &all, &all, (-7, 7), 3);
        for p in 0..w * h {
            assert_eq!(got[p].k != NONE, want[p].is_some());
            if let Some((k, _)) = want[p] {
                assert_eq!(got[p].k as usize, k, "pixel {p}");
            }
        }
    }

    #[test]
    fn a_bars_top_and_rim_take_the_tops_parallax_not_the_outlines() {
        let (w, h, top) = (96usize, 64usize, 4.0f32);
        let (a, b) = bar_pair(w, h, top);
        let valid = vec![true; w * h];
        for floor_unknown in [false, true] {
            // The outline's disparity, as a window matcher straddling it measures.
            let mut raw = Image::from_vec(w, h, vec![-top / 2.0; w * h]).unwrap();
            let mut conf = Image::zeros(w, h);
            let mut unknown = vec![Unknown::Measured; w * h];
            let q = SlantedParams {
                plateau: true,
                plateau_floor_unknown: floor_unknown,
                ..SlantedParams::default()
            };
            let out = (&mut raw, &mut conf, &mut unknown[..]);
            let n = measure_plateaus((&a, &b), (&valid, &valid), out, &q);
            assert!(n > 200, "{n} plateau pixels measured");
            let d = |x: usize| raw.data()[32 * w + x];
            // Middle of the top, and its rim on the outline.
            for x in [46, 30, 61] {
                assert!(
                    (d(x) + top).abs() < 0.3,
                    "x {x}: {}, expected {}",
                    d(x),
                    -top
                );
            }
            // The dark floor is left alone, or unknown on request.
            if floor_unknown {
                assert!(d(10).is_nan());
                assert_eq!(unknown[32 * w + 10], Unknown::NoTexture);
            } else {
                assert_eq!(d(10), -top / 2.0);
            }
        }
    }

    /// Where the matcher already measured the top (the outline moves with it), the plateau is
    /// left as it was; so is a plateau smaller than `plateau_min_px`.
    #[test]
    fn a_plateau_the_matcher_measured_or_too_small_is_left_alone() {
        let (w, h, top) = (96usize, 64usize, 4.0f32);
        let (a, _) = bar_pair(w, h, top);
        // The whole bar, outline and top texture, moved by the top's parallax.
        let b = Image::from_fn(w, h, |x, y| {
            let xf = x as f32 + top;
            if x as f32 + top >= 30.0 && xf < 62.0 {
                a.get(x + 4, y)
            } else {
                0.1
            }
        });
        let valid = vec![true; w * h];
        let q = SlantedParams {
            plateau: true,
            ..SlantedParams::default()
        };
        let run = |b: &Image, start: f32, q: &SlantedParams| {
            let mut raw = Image::from_vec(w, h, vec![start; w * h]).unwrap();
            let mut conf = Image::zeros(w, h);
            let mut unknown = vec![Unknown::LeftRight; w * h];
            let out = (&mut raw, &mut conf, &mut unknown[..]);
            let n = measure_plateaus((&a, b), (&valid, &valid), out, q);
            (n, raw)
        };
        let (n, raw) = run(&b, -top, &q);
        assert_eq!(n, 0);
        assert!(raw.data().iter().all(|d| *d == -top));
        // The same pair with the matcher half-way: the top is taken.
        let (n, raw) = run(&b, -top / 2.0, &q);
        assert!(n > 200, "{n}");
        assert!((raw.data()[32 * w + 46] + top).abs() < 0.3);
        // A bar of about 1800 pixels, below the least plateau asked for.
        let small = SlantedParams {
            plateau_min_px: 2500,
            ..q
        };
        assert_eq!(run(&b, -top / 2.0, &small).0, 0);
    }
}
