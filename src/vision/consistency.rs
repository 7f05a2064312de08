//! Left–right consistency of two dense correspondence fields (beyond the
//! paper, whose §4.3 leaves occlusion to future work).
//!
//! A pixel `p` of the left image matched to `q = p + (u, v)` in the right one
//! is consistent when the right-to-left field at `q` leads back to `p`:
//! `|(u, v)(p) + (u', v')(q)| ≤ τ`. Pixels seen by one camera only
//! (occlusions at depth steps) and mismatches fail the check.

use rayon::prelude::*;

use super::Image;

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
                if let (Some(bu), Some(bv)) =
                    (ur.sample_bilinear(qx, qy), vr.sample_bilinear(qx, qy))
                {
                    *r = (du + bu).hypot(dv + bv);
                }
            }
        });
    residual
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
        .iter()
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

#[cfg(test)]
mod tests {
    use super::*;

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
