//! Deterministic procedural noise: hashes, gradient noise, fBm, cellular noise.
//!
//! Everything is a pure function of a seed and the coordinates, so a scene,
//! its texture and the scan noise are reproducible and can be evaluated at any
//! point in any order (in parallel, at sub-pixel positions for ground truth).

/// SplitMix64 finaliser: a fast, well-mixed 64-bit hash.
#[inline]
#[must_use]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a seed and two lattice coordinates.
#[inline]
#[must_use]
pub fn hash2(seed: u64, i: i64, j: i64) -> u64 {
    // Reinterpreting the signed lattice indices as bits is intended.
    #[allow(clippy::cast_sign_loss)]
    let (a, b) = (i as u64, j as u64);
    mix64(seed ^ a.wrapping_mul(0xD6E8_FEB8_6659_FD93) ^ b.wrapping_mul(0xA076_1D64_78BD_642F))
}

/// Uniform in `[0, 1)` from the top 53 bits of a hash.
#[inline]
#[must_use]
pub fn unit(h: u64) -> f64 {
    // 53 bits fit the f64 mantissa exactly.
    #[allow(clippy::cast_precision_loss)]
    let v = (h >> 11) as f64;
    v * (1.0 / (1u64 << 53) as f64)
}

/// A sub-stream seed, so that different uses of one scene seed never correlate.
#[inline]
#[must_use]
pub fn substream(seed: u64, tag: u64) -> u64 {
    mix64(seed ^ mix64(tag.wrapping_add(0x5851_F42D_4C95_7F2D)))
}

/// Standard normal deviate from a hash (Box–Muller on two 32-bit halves).
#[inline]
#[must_use]
pub fn gaussian(h: u64) -> f64 {
    let u1 = ((h >> 32) as f64 + 0.5) / 4_294_967_296.0;
    let u2 = ((h & 0xFFFF_FFFF) as f64) / 4_294_967_296.0;
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[inline]
fn quintic(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Lattice coordinates of `x`: the cell index and the fraction in `[0, 1)`.
#[inline]
#[allow(clippy::cast_possible_truncation)]
fn lattice(x: f64) -> (i64, f64) {
    let f = x.floor();
    (f as i64, x - f)
}

/// Sixteen unit gradients, 22.5° apart (a table: trigonometry per lattice node
/// would dominate the cost of texturing a frame).
const R2: f64 = std::f64::consts::FRAC_1_SQRT_2;
const GRADIENTS: [(f64, f64); 16] = [
    (1.0, 0.0),
    (0.923_879_532_511_286_7, 0.382_683_432_365_089_8),
    (R2, R2),
    (0.382_683_432_365_089_8, 0.923_879_532_511_286_7),
    (0.0, 1.0),
    (-0.382_683_432_365_089_8, 0.923_879_532_511_286_7),
    (-R2, R2),
    (-0.923_879_532_511_286_7, 0.382_683_432_365_089_8),
    (-1.0, 0.0),
    (-0.923_879_532_511_286_7, -0.382_683_432_365_089_8),
    (-R2, -R2),
    (-0.382_683_432_365_089_8, -0.923_879_532_511_286_7),
    (0.0, -1.0),
    (0.382_683_432_365_089_8, -0.923_879_532_511_286_7),
    (R2, -R2),
    (0.923_879_532_511_286_7, -0.382_683_432_365_089_8),
];

/// Gradient of one lattice node: a unit vector chosen by the hash.
#[inline]
fn grad_dot(seed: u64, i: i64, j: i64, dx: f64, dy: f64) -> f64 {
    // The top four bits of the hash pick the gradient.
    #[allow(clippy::cast_possible_truncation)]
    let (cs, sn) = GRADIENTS[(hash2(seed, i, j) >> 60) as usize];
    cs * dx + sn * dy
}

/// 2-D gradient (Perlin) noise with unit lattice spacing, roughly in `[-0.7, 0.7]`.
#[must_use]
pub fn gradient_noise(seed: u64, x: f64, y: f64) -> f64 {
    let (i, fx) = lattice(x);
    let (j, fy) = lattice(y);
    let n00 = grad_dot(seed, i, j, fx, fy);
    let n10 = grad_dot(seed, i + 1, j, fx - 1.0, fy);
    let n01 = grad_dot(seed, i, j + 1, fx, fy - 1.0);
    let n11 = grad_dot(seed, i + 1, j + 1, fx - 1.0, fy - 1.0);
    let (u, v) = (quintic(fx), quintic(fy));
    let a = n00 + u * (n10 - n00);
    let b = n01 + u * (n11 - n01);
    a + v * (b - a)
}

/// Weight of a detail of wavelength `lambda` seen with a sampling footprint
/// `footprint` (both µm): 1 for details wider than 2.5 footprints, 0 below one
/// footprint. This band-limits procedural texture to what a pixel can show,
/// instead of aliasing it into noise that differs between views.
#[inline]
#[must_use]
pub fn lod_weight(lambda: f64, footprint: f64) -> f64 {
    if footprint <= 0.0 {
        return 1.0;
    }
    let t = ((lambda / footprint - 1.0) / 1.5).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Fractional Brownian motion: `octaves` octaves of gradient noise, the
/// coarsest of wavelength `lambda0` (µm), each next one `1/2` the wavelength
/// and `gain` the amplitude. Octaves finer than the footprint fade out.
#[must_use]
pub fn fbm(
    seed: u64,
    x: f64,
    y: f64,
    lambda0: f64,
    octaves: u32,
    gain: f64,
    footprint: f64,
) -> f64 {
    let mut sum = 0.0;
    let mut amp = 1.0;
    let mut lambda = lambda0;
    for o in 0..octaves {
        let w = lod_weight(lambda, footprint);
        if w <= 0.0 {
            break;
        }
        let s = mix64(seed ^ u64::from(o + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        sum += w * amp * gradient_noise(s, x / lambda, y / lambda);
        amp *= gain;
        lambda *= 0.5;
    }
    sum
}

/// Cellular (Worley) noise with unit cell size: distances to the nearest and
/// second-nearest feature point, and the hash of the nearest one's cell.
#[must_use]
pub fn cellular(seed: u64, x: f64, y: f64) -> (f64, f64, u64) {
    let (i, fx) = lattice(x);
    let (j, fy) = lattice(y);
    let mut f1 = f64::INFINITY;
    let mut f2 = f64::INFINITY;
    let mut id = 0;
    for dj in -1..=1 {
        for di in -1..=1 {
            let h = hash2(seed, i + di, j + dj);
            // Two 24-bit fractions of one hash place the feature point.
            #[allow(clippy::cast_precision_loss)]
            let px = di as f64 + 0.1 + 0.8 * ((h >> 40) as f64 / 16_777_216.0) - fx;
            #[allow(clippy::cast_precision_loss)]
            let py = dj as f64 + 0.1 + 0.8 * (((h >> 16) & 0xFF_FFFF) as f64 / 16_777_216.0) - fy;
            let d = px * px + py * py;
            if d < f1 {
                f2 = f1;
                f1 = d;
                id = h;
            } else if d < f2 {
                f2 = d;
            }
        }
    }
    (f1.sqrt(), f2.sqrt(), mix64(id))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_and_seed_dependent() {
        let a = gradient_noise(1, 3.3, -7.1);
        assert_eq!(a, gradient_noise(1, 3.3, -7.1));
        assert_ne!(a, gradient_noise(2, 3.3, -7.1));
    }

    #[test]
    fn gradient_noise_is_continuous_and_zero_on_lattice() {
        assert!(gradient_noise(5, 4.0, -2.0).abs() < 1e-12);
        let a = gradient_noise(5, 4.5, 1.25);
        let b = gradient_noise(5, 4.5 + 1e-6, 1.25);
        assert!((a - b).abs() < 1e-5);
    }

    #[test]
    fn gaussian_has_unit_variance() {
        let n = 20_000;
        let (mut s, mut s2) = (0.0, 0.0);
        for k in 0..n {
            let g = gaussian(mix64(k));
            s += g;
            s2 += g * g;
        }
        let mean = s / f64::from(n as u32);
        let var = s2 / f64::from(n as u32) - mean * mean;
        assert!(mean.abs() < 0.03, "mean {mean}");
        assert!((var - 1.0).abs() < 0.05, "var {var}");
    }

    #[test]
    fn lod_removes_fine_octaves() {
        assert_eq!(lod_weight(0.1, 0.2), 0.0);
        assert_eq!(lod_weight(1.0, 0.2), 1.0);
        // Coarse footprint: only the first octave (λ = 4) survives, attenuated.
        let coarse = fbm(3, 0.37, 0.91, 4.0, 6, 0.5, 3.0);
        let first = gradient_noise(mix64(3 ^ 0x9E37_79B9_7F4A_7C15), 0.37 / 4.0, 0.91 / 4.0);
        assert!((coarse - lod_weight(4.0, 3.0) * first).abs() < 1e-12);
        assert!(fbm(3, 0.37, 0.91, 4.0, 6, 0.5, 5.0).abs() < 1e-12);
    }

    #[test]
    fn cellular_orders_distances() {
        for k in 0..100 {
            let (f1, f2, _) = cellular(9, f64::from(k) * 0.37, f64::from(k) * 0.11);
            assert!(f1 <= f2);
        }
    }
}
