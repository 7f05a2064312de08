//! Translation between two frames by phase correlation (Kuglin & Hines 1975),
//! used to track the specimen between the quick frames of a tilt series.
//!
//! The normalised cross-power spectrum of two images related by a shift has an
//! inverse transform that is a delta at that shift. A Hann window tames the
//! discontinuity at the borders that the FFT's periodicity would otherwise
//! turn into a false peak at zero shift, and the band-limited correlation surface, evaluated on a
//! fine grid around the peak, gives the sub-pixel position.

use rustfft::{FftPlanner, num_complex::Complex32};

use super::Image;

/// Parameters of [`phase_correlation`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhaseCorrelationParams {
    /// Largest shift searched, as a fraction of the frame's smaller side.
    /// Shifts beyond half the frame are aliased by the FFT and cannot be
    /// told apart from their wrapped counterparts. Default 0.4.
    pub max_shift_fraction: f64,
    /// Smallest accepted ratio of the correlation peak to the mean absolute
    /// correlation surface; below it the shift is reported unreliable.
    /// Default 8.
    pub min_peak_ratio: f64,
}

impl Default for PhaseCorrelationParams {
    fn default() -> Self {
        Self {
            max_shift_fraction: 0.4,
            min_peak_ratio: 8.0,
        }
    }
}

/// The measured translation of `moved` relative to `reference`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Shift {
    /// Content moved by `dx` pixels towards +x from reference to moved.
    pub dx: f64,
    /// Content moved by `dy` pixels towards +y.
    pub dy: f64,
    /// Peak height over the mean absolute correlation: how distinct the match is.
    pub peak_ratio: f64,
}

/// Why a shift could not be measured.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistrationError {
    #[error("frames differ in size: {a_width}×{a_height} vs {b_width}×{b_height}")]
    SizeMismatch {
        a_width: usize,
        a_height: usize,
        b_width: usize,
        b_height: usize,
    },
    #[error("frame of {width}×{height} is too small to register (need at least 16×16)")]
    TooSmall { width: usize, height: usize },
    #[error(
        "no reliable shift between the frames: correlation peak ratio {peak_ratio:.1} < {min_peak_ratio:.1} \
         (is the specimen in view and in focus?)"
    )]
    Unreliable {
        peak_ratio: f64,
        min_peak_ratio: f64,
    },
}

/// Measures how far the content of `moved` is shifted relative to `reference`.
///
/// # Errors
/// [`RegistrationError`] when the sizes differ, the frames are tiny, or no
/// distinct correlation peak exists (blank, out-of-focus or unrelated frames).
pub fn phase_correlation(
    reference: &Image,
    moved: &Image,
    params: &PhaseCorrelationParams,
) -> Result<Shift, RegistrationError> {
    let (w, h) = reference.dimensions();
    if moved.dimensions() != (w, h) {
        return Err(RegistrationError::SizeMismatch {
            a_width: w,
            a_height: h,
            b_width: moved.width(),
            b_height: moved.height(),
        });
    }
    if w < 16 || h < 16 {
        return Err(RegistrationError::TooSmall {
            width: w,
            height: h,
        });
    }

    let mut fa = windowed(reference);
    let mut fb = windowed(moved);
    let mut planner = FftPlanner::<f32>::new();
    fft2(&mut planner, &mut fa, w, h, false);
    fft2(&mut planner, &mut fb, w, h, false);

    // Cross-power spectrum B·conj(A)/|B·conj(A)|: its inverse peaks at the shift of b relative to a.
    // A Gaussian low-pass on the whitened spectrum: the highest frequencies of
    // real frames carry aliasing and noise whose phase does not follow the shift.
    for (i, (a, b)) in fa.iter_mut().zip(&fb).enumerate() {
        let c = b * a.conj();
        let norm = c.norm();
        let (fx, fy) = (
            signed_index(i % w, w) as f32 / w as f32,
            signed_index(i / w, h) as f32 / h as f32,
        );
        let weight = (-(fx * fx + fy * fy) / (2.0 * LOW_PASS_SIGMA * LOW_PASS_SIGMA)).exp();
        *a = if norm > 1e-12 {
            c * (weight / norm)
        } else {
            Complex32::new(0.0, 0.0)
        };
    }
    let spectrum = fa.clone();
    fft2(&mut planner, &mut fa, w, h, true);
    let surface: Vec<f32> = fa.iter().map(|c| c.re).collect();

    let max_shift = (params.max_shift_fraction * w.min(h) as f64).max(1.0);
    let (px, py, peak) = find_peak(&surface, w, h, max_shift);
    let mean_abs = surface.iter().map(|v| f64::from(v.abs())).sum::<f64>() / surface.len() as f64;
    let peak_ratio = if mean_abs > 0.0 {
        f64::from(peak) / mean_abs
    } else {
        0.0
    };
    if peak_ratio.is_nan() || peak_ratio < params.min_peak_ratio {
        return Err(RegistrationError::Unreliable {
            peak_ratio,
            min_peak_ratio: params.min_peak_ratio,
        });
    }

    let (dx, dy) = refine_peak(&spectrum, w, h, signed_index(px, w), signed_index(py, h));
    Ok(Shift { dx, dy, peak_ratio })
}

/// Standard deviation of the low-pass weight on the cross-power spectrum, cycles/pixel.
const LOW_PASS_SIGMA: f32 = 0.12;

/// Sub-pixel refinement factor of the peak: the correlation is evaluated on a
/// grid of 1/`UPSAMPLE` pixel around the integer peak.
const UPSAMPLE: usize = 20;

/// Locates the correlation maximum to 1/[`UPSAMPLE`] px by evaluating the
/// band-limited correlation surface (the inverse DFT of the normalised
/// cross-power spectrum `spectrum`) on a fine grid around the integer peak —
/// the matrix-multiply DFT of Guizar-Sicairos, Thurman & Fienup (2008). Unlike
/// a parabola through three samples it has no bias towards integer shifts.
fn refine_peak(spectrum: &[Complex32], w: usize, h: usize, px: isize, py: isize) -> (f64, f64) {
    let n = 2 * UPSAMPLE + 1;
    let offsets: Vec<f64> = (0..n)
        .map(|k| (k as f64 - UPSAMPLE as f64) / UPSAMPLE as f64)
        .collect();
    let freq = |i: usize, len: usize| signed_index(i, len) as f64 / len as f64;
    // Separable evaluation: first along x for every frequency row, then along y.
    let kernel = |len: usize, centre: isize| -> Vec<Complex32> {
        let mut k = Vec::with_capacity(len * n);
        for i in 0..len {
            let f = freq(i, len);
            for &o in &offsets {
                let phase = std::f64::consts::TAU * f * (centre as f64 + o);
                k.push(Complex32::new(phase.cos() as f32, phase.sin() as f32));
            }
        }
        k
    };
    let kx = kernel(w, px);
    let ky = kernel(h, py);
    // rows[v][j] = Σ_u S(u, v) · e^{2πi u x_j / W}
    let mut rows = vec![Complex32::new(0.0, 0.0); h * n];
    for v in 0..h {
        let srow = &spectrum[v * w..(v + 1) * w];
        let out = &mut rows[v * n..(v + 1) * n];
        for (u, s) in srow.iter().enumerate() {
            let k = &kx[u * n..(u + 1) * n];
            for (o, kk) in out.iter_mut().zip(k) {
                *o += s * kk;
            }
        }
    }
    let mut best = (0usize, 0usize, f32::NEG_INFINITY);
    for i in 0..n {
        for j in 0..n {
            let mut acc = Complex32::new(0.0, 0.0);
            for v in 0..h {
                acc += rows[v * n + j] * ky[v * n + i];
            }
            if acc.re > best.2 {
                best = (j, i, acc.re);
            }
        }
    }
    (px as f64 + offsets[best.0], py as f64 + offsets[best.1])
}

/// The image minus its mean, times a separable Hann window, as complex samples.
fn windowed(img: &Image) -> Vec<Complex32> {
    let (w, h) = img.dimensions();
    let mean = img.data().iter().map(|&v| f64::from(v)).sum::<f64>() / img.len() as f64;
    let hann = |i: usize, n: usize| -> f32 {
        let t = std::f64::consts::TAU * i as f64 / (n - 1) as f64;
        (0.5 - 0.5 * t.cos()) as f32
    };
    let wx: Vec<f32> = (0..w).map(|i| hann(i, w)).collect();
    let wy: Vec<f32> = (0..h).map(|i| hann(i, h)).collect();
    let mut out = Vec::with_capacity(w * h);
    for (y, wy) in wy.iter().enumerate() {
        for (v, wx) in img.row(y).iter().zip(&wx) {
            out.push(Complex32::new((v - mean as f32) * wx * wy, 0.0));
        }
    }
    out
}

/// In-place 2D FFT (rows, then columns); `inverse` is unnormalised.
fn fft2(planner: &mut FftPlanner<f32>, data: &mut [Complex32], w: usize, h: usize, inverse: bool) {
    let row_fft = if inverse {
        planner.plan_fft_inverse(w)
    } else {
        planner.plan_fft_forward(w)
    };
    row_fft.process(data);
    let col_fft = if inverse {
        planner.plan_fft_inverse(h)
    } else {
        planner.plan_fft_forward(h)
    };
    let mut column = vec![Complex32::new(0.0, 0.0); h];
    for x in 0..w {
        for (y, c) in column.iter_mut().enumerate() {
            *c = data[y * w + x];
        }
        col_fft.process(&mut column);
        for (y, c) in column.iter().enumerate() {
            data[y * w + x] = *c;
        }
    }
}

/// Position and value of the highest sample whose wrapped shift is within `max_shift`.
fn find_peak(surface: &[f32], w: usize, h: usize, max_shift: f64) -> (usize, usize, f32) {
    let mut best = (0, 0, f32::NEG_INFINITY);
    for y in 0..h {
        let sy = signed_index(y, h) as f64;
        if sy.abs() > max_shift {
            continue;
        }
        for x in 0..w {
            let sx = signed_index(x, w) as f64;
            if sx.abs() > max_shift {
                continue;
            }
            let v = surface[y * w + x];
            if v > best.2 {
                best = (x, y, v);
            }
        }
    }
    best
}

/// FFT index to signed shift: indices past the middle wrap to negative shifts.
fn signed_index(i: usize, n: usize) -> isize {
    if i > n / 2 {
        i as isize - n as isize
    } else {
        i as isize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Broadband texture: value noise (a hash per lattice point, bilinear in
    /// between) at two scales, defined everywhere so shifted copies are exact.
    fn texture(x: f64, y: f64) -> f32 {
        fn hash(i: i64, j: i64) -> f64 {
            let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            h ^= h >> 31;
            h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            h ^= h >> 29;
            (h >> 11) as f64 / (1u64 << 53) as f64
        }
        fn value_noise(x: f64, y: f64) -> f64 {
            let (i, j) = (x.floor(), y.floor());
            let (fx, fy) = (x - i, y - j);
            let (i, j) = (i as i64, j as i64);
            let top = hash(i, j) * (1.0 - fx) + hash(i + 1, j) * fx;
            let bottom = hash(i, j + 1) * (1.0 - fx) + hash(i + 1, j + 1) * fx;
            top * (1.0 - fy) + bottom * fy
        }
        (value_noise(x / 2.5, y / 2.5) + 0.5 * value_noise(x / 7.0 + 100.0, y / 7.0)) as f32
    }

    fn shifted(w: usize, h: usize, dx: f64, dy: f64) -> Image {
        Image::from_fn(w, h, |x, y| texture(x as f64 - dx, y as f64 - dy))
    }

    #[test]
    fn recovers_integer_and_subpixel_shifts() {
        let reference = shifted(128, 96, 0.0, 0.0);
        for &(dx, dy) in &[
            (0.0, 0.0),
            (5.0, -3.0),
            (-12.0, 7.0),
            (2.4, -1.7),
            (-0.3, 0.6),
        ] {
            let moved = shifted(128, 96, dx, dy);
            let s =
                phase_correlation(&reference, &moved, &PhaseCorrelationParams::default()).unwrap();
            assert!(
                (s.dx - dx).abs() < 0.06 && (s.dy - dy).abs() < 0.06,
                "expected ({dx}, {dy}), got ({}, {})",
                s.dx,
                s.dy
            );
        }
    }

    #[test]
    fn sign_follows_content_motion() {
        // A bright square moves right and down by (6, 4).
        let square = |ox: usize, oy: usize| {
            Image::from_fn(64, 64, move |x, y| {
                let inside = x >= 20 + ox && x < 30 + ox && y >= 20 + oy && y < 30 + oy;
                if inside { 1.0 } else { 0.0 }
            })
        };
        let s = phase_correlation(
            &square(0, 0),
            &square(6, 4),
            &PhaseCorrelationParams::default(),
        )
        .unwrap();
        assert!(
            (s.dx - 6.0).abs() < 0.3 && (s.dy - 4.0).abs() < 0.3,
            "{s:?}"
        );
    }

    #[test]
    fn blank_frames_are_unreliable() {
        let blank = Image::filled(64, 64, 0.5);
        let err =
            phase_correlation(&blank, &blank, &PhaseCorrelationParams::default()).unwrap_err();
        assert!(matches!(err, RegistrationError::Unreliable { .. }), "{err}");
    }

    #[test]
    fn size_mismatch_is_refused() {
        let err = phase_correlation(
            &Image::zeros(64, 64),
            &Image::zeros(64, 32),
            &PhaseCorrelationParams::default(),
        )
        .unwrap_err();
        assert!(err.to_string().contains("64×64 vs 64×32"));
    }
}
