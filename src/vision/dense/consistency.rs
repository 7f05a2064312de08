//! Left–right consistency of two dense correspondence fields (beyond the
//! paper, whose §4.3 leaves occlusion to future work).
//!
//! A pixel `p` of the left image matched to `q = p + (u, v)` in the right one
//! is consistent when the right-to-left field at `q` leads back to `p`:
//! `|(u, v)(p) + (u', v')(q)| ≤ τ`. Pixels seen by one camera only
//! (occlusions at depth steps) and mismatches fail the check.

use rayon::prelude::*;

use crate::vision::Image;

/// Result of [`left_right_check`].
#[derive(Debug, Clone)]
pub struct Consistency {
    /// Per left pixel, the length of `(u, v)(p) + (u', v')(q)`, pixels
    /// (`NaN` where `q` falls outside the right image).
    pub residual: Image,
    /// Per left pixel: failed the check (residual above τ or `q` outside).
    pub rejected: Vec<bool>,
}

/// Checks the left-to-right field `(u, v)` against the right-to-left field
/// `(ur, vr)` with tolerance `tolerance` pixels. The backward field is read
/// with bilinear interpolation.
#[must_use]
pub fn left_right_check(
    u: &Image,
    v: &Image,
    ur: &Image,
    vr: &Image,
    tolerance: f32,
) -> Consistency {
    let residual = left_right_residual(u, v, ur, vr);
    let rejected = reject_beyond(&residual, (tolerance, tolerance), None);
    Consistency { residual, rejected }
}

/// The [`Consistency::residual`] of the left-to-right field `(u, v)` against
/// the right-to-left field `(ur, vr)`, for callers that apply their own
/// tolerances with [`reject_beyond`].
#[must_use]
pub fn left_right_residual(u: &Image, v: &Image, ur: &Image, vr: &Image) -> Image {
    let (w, h) = u.dimensions();
    assert!(
        v.dimensions() == (w, h) && ur.dimensions() == vr.dimensions(),
        "fields of one size each"
    );
    let mut residual = Image::filled(w, h, f32::NAN);
    residual
        .data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, r) in row.iter_mut().enumerate() {
                let (du, dv) = (u.get(x, y), v.get(x, y));
                let qx = f64::from(x as f32 + du);
                let qy = f64::from(y as f32 + dv);
                if let Some((bu, bv)) = sample_both(ur, vr, qx, qy) {
                    *r = length(du + bu, dv + bv);
                }
            }
        });
    residual
}

/// [`Image::sample_bilinear`] of two images of one size at the same point, the weights found
/// once; the same arithmetic, so the same values.
#[inline]
fn sample_both(a: &Image, b: &Image, x: f64, y: f64) -> Option<(f32, f32)> {
    let (w, h) = a.dimensions();
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
    // Non-negative and bounded by the checks above: truncation is the floor.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let (x0, y0) = (x as usize, y as usize);
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    #[allow(clippy::cast_possible_truncation)]
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let corners = ((x0, x1), (y0, y1));
    Some((
        bilinear(a, corners, (fx, fy)),
        bilinear(b, corners, (fx, fy)),
    ))
}

/// The bilinear interpolation of `img` between the columns `x0, x1` and rows `y0, y1` at
/// weights `(fx, fy)` of the second ones. Always inlined: called twice per pixel of the
/// check, a call (which the compiler's partitioning sometimes chose) cost 1.4 % of a run.
#[inline(always)]
fn bilinear(
    img: &Image,
    ((x0, x1), (y0, y1)): ((usize, usize), (usize, usize)),
    (fx, fy): (f32, f32),
) -> f32 {
    let top = img.get(x0, y0) * (1.0 - fx) + img.get(x1, y0) * fx;
    let bottom = img.get(x0, y1) * (1.0 - fx) + img.get(x1, y1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// `a.hypot(b)` without the library call: the squares of two `f32` are exact in `f64` and
/// their sum's root rounds as the C library's `hypotf` does (glibc ≥ 2.35 computes it so);
/// non-finite input takes the library's path.
#[inline]
fn length(a: f32, b: f32) -> f32 {
    if a.is_finite() && b.is_finite() {
        let (a, b) = (f64::from(a), f64::from(b));
        // The root of a sum of two f32 squares is within the f32 range or infinite, as hypotf's.
        #[allow(clippy::cast_possible_truncation)]
        let r = (a * a + b * b).sqrt() as f32;
        r
    } else {
        a.hypot(b)
    }
}

/// Per pixel of a [`Consistency::residual`]: whether it fails a left–right
/// check with tolerance `tolerances.0`, or `tolerances.1` where `smooth` is
/// set (`NaN`: the match left the other image, always a failure).
#[must_use]
pub fn reject_beyond(
    residual: &Image,
    tolerances: (f32, f32),
    smooth: Option<&[bool]>,
) -> Vec<bool> {
    residual
        .data()
        .par_iter()
        .enumerate()
        .map(|(p, &r)| {
            let tol = match smooth {
                Some(s) if s[p] => tolerances.0.max(tolerances.1),
                _ => tolerances.0,
            };
            r.is_nan() || r > tol
        })
        .collect()
}

/// The check of a matcher's fields `(u, v)` against `(ur, vr)` at their own
/// pyramid level: tolerance `tolerances.0` everywhere, and `tolerances.1` on
/// the horizontal component alone where `smooth` is set (away from depth
/// discontinuities). There the vertical flow of a weakly textured area
/// jitters by a label or two — the pair is rectified, its true vertical flow
/// a fraction of a pixel — and the refined fields' check judges it later at
/// full precision (Potamogeton: 0.4–0.7 point more of the image where two
/// pairs agree, at the same RMSE; the simulated cases unchanged).
#[must_use]
pub fn matcher_level_rejects(
    (u, v): (&Image, &Image),
    (ur, vr): (&Image, &Image),
    tolerances: (f32, f32),
    smooth: Option<&[bool]>,
) -> Vec<bool> {
    let strict = reject_beyond(
        &left_right_residual(u, v, ur, vr),
        (tolerances.0, tolerances.0),
        None,
    );
    let Some(smooth) = smooth else {
        return strict;
    };
    let zero = Image::zeros(u.width(), u.height());
    let horizontal = reject_beyond(
        &left_right_residual(u, &zero, ur, &zero),
        tolerances,
        Some(smooth),
    );
    strict
        .into_iter()
        .zip(horizontal)
        .zip(smooth)
        .map(|((s, h), &sm)| if sm { h } else { s })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shortcuts of the residual are the library's functions, bit for bit.
    #[test]
    fn residual_shortcuts_equal_the_library_functions() {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for i in 0..200_000 {
            let r = next();
            #[allow(clippy::cast_possible_truncation)]
            let (a, b) = if i % 2 == 0 {
                (f32::from_bits((r >> 32) as u32), f32::from_bits(r as u32))
            } else {
                (
                    ((r >> 40) as f32 / 16_777_216.0 - 0.5) * 8.0,
                    ((r & 0xff_ffff) as f32 / 16_777_216.0 - 0.5) * 8.0,
                )
            };
            let (want, got) = (a.hypot(b), length(a, b));
            assert!(
                want.to_bits() == got.to_bits() || (want.is_nan() && got.is_nan()),
                "hypot({a:e}, {b:e}) = {want:e}, not {got:e}"
            );
        }
        let a = Image::from_fn(7, 5, |x, y| (x * x) as f32 * 0.37 - y as f32 * 1.3);
        let b = Image::from_fn(7, 5, |x, y| (x + 3 * y) as f32 * -0.71);
        for i in 0..2000 {
            let r = next();
            let x = (r >> 40) as f64 / 16_777_216.0 * 8.0 - 0.5 + f64::from(i % 3);
            let y = (r & 0xff_ffff) as f64 / 16_777_216.0 * 6.0 - 0.5;
            let want = a.sample_bilinear(x, y).zip(b.sample_bilinear(x, y));
            assert_eq!(
                want.map(|(p, q)| (p.to_bits(), q.to_bits())),
                sample_both(&a, &b, x, y).map(|(p, q)| (p.to_bits(), q.to_bits())),
                "at ({x}, {y})"
            );
        }
    }

    /// Away from discontinuities a vertical disagreement of a few labels
    /// passes and a horizontal one beyond the wide tolerance fails; beside
    /// one the strict tolerance applies to both components.
    #[test]
    fn matcher_level_check_leaves_the_vertical_to_the_refined_check_where_smooth() {
        let (w, h) = (16, 4);
        let u = Image::filled(w, h, 2.0);
        let ur = Image::from_fn(w, h, |x, _| if x >= 10 { -5.5 } else { -2.0 });
        let v = Image::filled(w, h, 1.5);
        let vr = Image::filled(w, h, 1.5);
        let smooth: Vec<bool> = (0..w * h).map(|p| (p / w) < 2).collect();
        let r = matcher_level_rejects((&u, &v), (&ur, &vr), (1.0, 2.0), Some(&smooth));
        // Rows 0–1 smooth: x ≤ 7 lands on ur = −2 (horizontal residual 0,
        // vertical 3: passes), x ≥ 8 on −5.5 (3.5 > 2: fails).
        assert!(!r[w + 3]);
        assert!(r[w + 9]);
        // Rows 2–3 beside a discontinuity: the vertical 3 fails already.
        assert!(r[2 * w + 3]);
        // Without a smooth mask the strict check of both components.
        let strict = matcher_level_rejects((&u, &v), (&ur, &vr), (1.0, 2.0), None);
        assert!(strict.iter().all(|&x| x));
        let none = matcher_level_rejects(
            (&u, &Image::zeros(w, h)),
            (&ur, &Image::zeros(w, h)),
            (1.0, 2.0),
            None,
        );
        assert!(!none[3] && none[9]);
    }

    #[test]
    fn consistent_fields_pass_and_a_contradiction_fails() {
        let u = Image::filled(10, 4, 2.0);
        let v = Image::zeros(10, 4);
        let mut ur = Image::filled(10, 4, -2.0);
        // The right pixels that left x = 3 reaches claim a different match.
        ur.set(5, 1, 1.0);
        let c = left_right_check(&u, &v, &ur, &Image::zeros(10, 4), 1.0);
        assert!(!c.rejected[10 + 2]);
        assert!(c.rejected[10 + 3]);
        // Matches leaving the right image are rejected.
        assert!(c.rejected[9]);
        assert!(c.residual.get(9, 0).is_nan());
    }

    #[test]
    fn the_wider_tolerance_applies_only_where_the_flow_is_smooth() {
        let residual = Image::from_vec(4, 1, vec![3.0, 3.0, 1.0, f32::NAN]).unwrap();
        let smooth = [true, false, false, true];
        assert_eq!(
            reject_beyond(&residual, (2.0, 4.0), Some(&smooth)),
            [false, true, false, true]
        );
        assert_eq!(
            reject_beyond(&residual, (2.0, 4.0), None),
            [true, true, false, true]
        );
        // A "wider" tolerance below the base one changes nothing.
        assert_eq!(
            reject_beyond(&residual, (2.0, 1.0), Some(&smooth)),
            [true, true, false, true]
        );
    }
}
