//! Interpolation of short gaps in the disparity along the epipolar lines.
//!
//! The left–right check leaves holes where a match could not be trusted: the
//! background beside a raised feature that the other micrograph does not see
//! (an occlusion), a steep flank squeezed into a few pixels of the other
//! view, a weakly textured patch whose two fields disagree. A run of unknown
//! pixels along a row of the rectified canvas that has a measured disparity
//! at both ends, lies wholly inside the left image and is at most `max_gap`
//! pixels long is filled by linear interpolation between its two ends — an
//! estimate, not a measurement: the caller keeps the mask of filled pixels
//! and gives them no confidence. Runs that touch the image's border (a strip
//! the other micrograph never saw) or longer runs stay unknown; nothing is
//! extrapolated.
//!
//! Rows, because after rectification the parallax is horizontal: the
//! disparity varies along a row with the relief and a rejected run ends on
//! the measured surface on either side of it.

use rayon::prelude::*;

use crate::vision::Image;

/// Fills the runs of non-finite values of `disparity` that are bounded on
/// both ends by finite values of the same row, lie inside `inside` (the
/// left image's pixels on the canvas) and are at most `max_gap` pixels long,
/// by linear interpolation between the two ends. Returns the mask of the
/// pixels filled; `max_gap = 0` fills nothing.
///
/// # Panics
/// If `inside` does not have one entry per pixel.
pub fn fill_row_gaps(disparity: &mut Image, inside: &[bool], max_gap: usize) -> Vec<bool> {
    let w = disparity.width();
    assert_eq!(inside.len(), disparity.len(), "one mask entry per pixel");
    let mut filled = vec![false; disparity.len()];
    if max_gap == 0 || w == 0 {
        return filled;
    }
    disparity
        .data_mut()
        .par_chunks_mut(w)
        .zip(filled.par_chunks_mut(w))
        .zip(inside.par_chunks(w))
        .for_each(|((row, done), ins)| fill_row(row, done, ins, max_gap));
    filled
}

fn fill_row(row: &mut [f32], done: &mut [bool], inside: &[bool], max_gap: usize) {
    // `last`: the latest finite pixel with no outside pixel after it.
    let mut last: Option<usize> = None;
    for x in 0..row.len() {
        if !inside[x] {
            last = None;
        } else if row[x].is_finite() {
            if let Some(a) = last {
                let gap = x - a - 1;
                if gap > 0 && gap <= max_gap {
                    let (da, db) = (row[a], row[x]);
                    let span = (x - a) as f32;
                    for (k, q) in (a + 1..x).enumerate() {
                        let t = (k + 1) as f32 / span;
                        row[q] = da + t * (db - da);
                    }
                    done[a + 1..x].fill(true);
                }
            }
            last = Some(x);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row_image(values: &[f32]) -> Image {
        Image::from_vec(values.len(), 1, values.to_vec()).unwrap()
    }

    #[test]
    fn a_bounded_gap_is_interpolated_linearly_and_marked() {
        let n = f32::NAN;
        let mut d = row_image(&[1.0, 2.0, n, n, n, 6.0, 7.0]);
        let filled = fill_row_gaps(&mut d, &[true; 7], 3);
        assert_eq!(d.data(), &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        assert_eq!(
            filled,
            [false, false, true, true, true, false, false].to_vec()
        );
    }

    #[test]
    fn nothing_is_extrapolated_past_the_last_measured_pixel() {
        let n = f32::NAN;
        let mut d = row_image(&[n, n, 3.0, n, 5.0, n]);
        let filled = fill_row_gaps(&mut d, &[true; 6], 10);
        assert!(d.data()[0].is_nan() && d.data()[1].is_nan() && d.data()[5].is_nan());
        assert_eq!(d.data()[3], 4.0);
        assert_eq!(filled.iter().filter(|&&f| f).count(), 1);
    }

    #[test]
    fn a_gap_longer_than_the_limit_or_crossing_the_border_stays_unknown() {
        let n = f32::NAN;
        let mut d = row_image(&[1.0, n, n, n, 5.0]);
        assert!(!fill_row_gaps(&mut d, &[true; 5], 2).contains(&true));
        assert!(d.data()[2].is_nan());
        // The same gap with a pixel outside the left image in it.
        let mut d = row_image(&[1.0, n, n, n, 5.0]);
        let inside = [true, true, false, true, true];
        assert!(!fill_row_gaps(&mut d, &inside, 10).contains(&true));
        assert_eq!(fill_row_gaps(&mut d, &[true; 5], 0), vec![false; 5]);
    }

    #[test]
    fn rows_are_filled_independently() {
        let n = f32::NAN;
        let mut d = Image::from_vec(3, 2, vec![0.0, n, 2.0, n, n, 4.0]).unwrap();
        let filled = fill_row_gaps(&mut d, &[true; 6], 5);
        assert_eq!(d.data()[1], 1.0);
        assert!(d.data()[3].is_nan() && d.data()[4].is_nan());
        assert_eq!(filled, vec![false, true, false, false, false, false]);
    }
}
