//! Plateaus measured apart from their outline (beyond the paper; opt-in, `slanted.plateau`).
//!
//! A raised, nearly featureless plateau with walls steeper than half the tilt (the bars of a
//! calibration grid) shows each view a wall the other does not: its bright outline, the
//! strongest texture, moves by about half the top's parallax, and a window that straddles it
//! measures the top at about half its height. Here the bright, flat pixels of the left canvas
//! (above the midpoint of its brightness range, gradient below `plateau_max_gradient` of that
//! range, one pixel in from the rest) are matched again with box windows restricted to that
//! mask, so the outline does not enter: zero-mean NCC at every integer disparity within
//! `plateau_reach` of the field's range over the mask, a parabola through the best three.
//! A pixel takes the new disparity when its peak reaches `plateau_min_ncc`.

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
    vals.sort_by(f32::total_cmp);
    let pct = |q: f64| vals[((vals.len() - 1) as f64 * q) as usize];
    let (lo, hi) = (pct(0.10), pct(0.99));
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
    let finite = raw
        .data()
        .iter()
        .zip(&mask)
        .filter(|(d, m)| **m && d.is_finite())
        .map(|(d, _)| *d);
    let (lo, hi) = finite.fold((f32::INFINITY, f32::NEG_INFINITY), |(l, u), d| {
        (l.min(d), u.max(d))
    });
    if !lo.is_finite() {
        return 0;
    }
    let first = (lo - q.plateau_reach).floor() as i64;
    let last = (hi + q.plateau_reach).ceil() as i64;
    let r = q.plateau_radius;
    let (ad, bd) = (a.data(), b.data());
    // Normalised cross-correlation at each integer disparity, over the masked box windows.
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
                    .into_par_iter()
                    .map(|p| sample(p).map_or(0.0, |(x, y)| f(x, y)))
                    .collect();
                box_sum(&v, w, h, r)
            };
            let n = terms(|_, _| 1.0);
            let sa = terms(|x, _| x);
            let sb = terms(|_, y| y);
            let saa = terms(|x, _| x * x);
            let sbb = terms(|_, y| y * y);
            let sab = terms(|x, y| x * y);
            (0..w * h)
                .into_par_iter()
                .map(|p| {
                    if n[p] < 4.0 {
                        return f32::NAN;
                    }
                    let (ma, mb) = (sa[p] / n[p], sb[p] / n[p]);
                    let vaa = saa[p] / n[p] - ma * ma;
                    let vbb = sbb[p] / n[p] - mb * mb;
                    let cab = sab[p] / n[p] - ma * mb;
                    let den = (vaa * vbb).sqrt();
                    if den > 0.0 {
                        (cab / den) as f32
                    } else {
                        f32::NAN
                    }
                })
                .collect()
        })
        .collect();
    let mut changed = 0;
    let mut took = vec![false; w * h];
    let (rd, cd) = (raw.data_mut(), confidence.data_mut());
    for p in (0..w * h).filter(|&p| mask[p]) {
        let z = |k: usize| scores[k][p];
        let best = (0..scores.len())
            .filter(|&k| z(k).is_finite())
            .max_by(|&i, &j| z(i).total_cmp(&z(j)));
        let Some(k) = best else { continue };
        if k == 0 || k + 1 == scores.len() || z(k) < q.plateau_min_ncc {
            continue;
        }
        let (zm, z0, zp) = (z(k - 1), z(k), z(k + 1));
        let den = zm - 2.0 * z0 + zp;
        let off = if den < 0.0 && den.is_finite() {
            (0.5 * (zm - zp) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        rd[p] = (first + k as i64) as f32 + off;
        // Not below the matcher's: the weighted filter must not let the outline's pixels win.
        cd[p] = cd[p].max(z0.clamp(0.0, 1.0));
        unknown[p] = Unknown::Measured;
        took[p] = true;
        changed += 1;
    }
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
}
