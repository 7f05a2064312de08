//! Synthetic rectified stereo pairs with exact ground truth, for tests,
//! benchmarks and the dense-stage evaluation while no renderer is at hand.
//!
//! The texture is band-limited value noise, a continuous function of `(x, y)`,
//! so the right image can be sampled exactly at sub-pixel positions. A scene is
//! a stack of layers, each with a smooth disparity `D_i(x, y)` (on the left
//! grid) and a region; the right image at `x'` shows the first layer, in
//! order, whose point `x` with `x + D_i(x, y) = x'` lies in its region — so a
//! nearer layer listed first occludes the ones behind it.

use crate::vision::Image;

/// Band-limited value noise in about `[0, 1]`.
#[derive(Debug, Clone, Copy)]
pub struct Texture {
    seed: u64,
}

fn hash(seed: u64, x: i64, y: i64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 33;
    h = h.wrapping_mul(0xC4CE_B9FE_1A85_EC53);
    h ^= h >> 33;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

impl Texture {
    #[must_use]
    pub fn new(seed: u64) -> Self {
        Self { seed }
    }

    /// Smooth lattice noise of one octave (quintic interpolation).
    fn octave(&self, x: f64, y: f64, o: u64) -> f64 {
        let (xf, yf) = (x.floor(), y.floor());
        let (xi, yi) = (xf as i64, yf as i64);
        let (tx, ty) = (x - xf, y - yf);
        let s = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
        let (sx, sy) = (s(tx), s(ty));
        let seed = self.seed.wrapping_add(o.wrapping_mul(0x1234_5678_9ABC));
        let a = hash(seed, xi, yi);
        let b = hash(seed, xi + 1, yi);
        let c = hash(seed, xi, yi + 1);
        let d = hash(seed, xi + 1, yi + 1);
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }

    /// The texture at a real position (pixels).
    #[must_use]
    pub fn at(&self, x: f64, y: f64) -> f64 {
        // Periods of 2.5, 5, 10 and 20 pixels: texture at the scales the
        // descriptors see, like a rough SEM surface.
        let mut v = 0.0;
        let mut norm = 0.0;
        for (o, (period, amp)) in [(2.5, 0.6), (5.0, 1.0), (10.0, 0.8), (20.0, 0.5)]
            .into_iter()
            .enumerate()
        {
            v += amp * self.octave(x / period, y / period, o as u64);
            norm += amp;
        }
        v / norm
    }
}

/// One surface of a synthetic scene.
pub struct Layer {
    /// Disparity on the left grid, pixels.
    pub disparity: Box<dyn Fn(f64, f64) -> f64 + Send + Sync>,
    /// Whether a left-grid point belongs to the layer.
    pub region: Box<dyn Fn(f64, f64) -> bool + Send + Sync>,
}

/// A rectified pair with its truth on the left grid.
pub struct SyntheticPair {
    pub left: Image,
    pub right: Image,
    /// True disparity of every left pixel (the layer it belongs to).
    pub disparity: Image,
    /// Left pixels visible in the right image.
    pub visible: Vec<bool>,
}

/// Renders `layers` (nearest first) over `texture`, with optional vertical
/// misalignment `dy` of the right image (rectification error) and additive
/// noise of standard deviation `noise`.
#[must_use]
pub fn render(
    width: usize,
    height: usize,
    texture: Texture,
    layers: &[Layer],
    dy: f64,
    noise: f64,
) -> SyntheticPair {
    let left = Image::from_fn(width, height, |x, y| texture.at(x as f64, y as f64) as f32);
    let layer_of = |x: f64, y: f64| layers.iter().position(|l| (l.region)(x, y));
    // The right image: for each pixel, the first layer that claims it.
    let right_point = |xr: f64, y: f64| -> Option<(f64, usize)> {
        for (i, l) in layers.iter().enumerate() {
            // Fixed point x = x' − D(x): converges for |∂D/∂x| < 1.
            let mut x = xr - (l.disparity)(xr, y);
            for _ in 0..30 {
                x = xr - (l.disparity)(x, y);
            }
            if (l.region)(x, y) && layer_of(x, y) == Some(i) {
                return Some((x, i));
            }
        }
        None
    };
    let mut seed = 0x5EED_u64;
    let mut gauss = move || {
        // Box–Muller on the hash.
        seed = seed.wrapping_add(1);
        let u1 = hash(seed, 1, 2).max(1e-12);
        let u2 = hash(seed, 3, 4);
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    };
    let right = Image::from_fn(width, height, |x, y| {
        let yl = y as f64 + dy;
        let v = match right_point(x as f64, yl) {
            Some((xl, _)) => texture.at(xl, yl),
            None => texture.at(x as f64 + 1000.0, yl),
        };
        (v + noise * gauss()) as f32
    });
    let mut left = left;
    if noise > 0.0 {
        for v in left.data_mut() {
            *v += (noise * gauss()) as f32;
        }
    }
    let mut disparity = Image::filled(width, height, f32::NAN);
    let mut visible = vec![false; width * height];
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f64, y as f64);
            if let Some(i) = layer_of(xf, yf) {
                let d = (layers[i].disparity)(xf, yf);
                disparity.set(x, y, d as f32);
                // Visible when the right image at x + d shows this very point.
                let xr = xf + d;
                visible[y * width + x] = xr >= 0.0
                    && xr <= (width - 1) as f64
                    && right_point(xr, yf).is_some_and(|(xl, j)| j == i && (xl - xf).abs() < 0.05);
            }
        }
    }
    SyntheticPair {
        left,
        right,
        disparity,
        visible,
    }
}

/// A spherical cap of `peak` pixels of disparity over a base of `base`
/// pixels, radius `radius` (fraction of the smaller side), centred.
#[must_use]
pub fn dome(width: usize, height: usize, base: f64, peak: f64, radius: f64) -> Vec<Layer> {
    let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
    let r = radius * width.min(height) as f64;
    vec![Layer {
        disparity: Box::new(move |x, y| {
            let q = ((x - cx).powi(2) + (y - cy).powi(2)) / (r * r);
            base + if q < 1.0 { peak * (1.0 - q) } else { 0.0 }
        }),
        region: Box::new(|_, _| true),
    }]
}

/// A raised vertical band `[x0, x1)` of disparity `base + step` in front of a
/// plane of disparity `base`: occludes a band of the plane next to it.
#[must_use]
pub fn raised_band(x0: f64, x1: f64, base: f64, step: f64) -> Vec<Layer> {
    vec![
        Layer {
            disparity: Box::new(move |_, _| base + step),
            region: Box::new(move |x, _| x >= x0 && x < x1),
        },
        Layer {
            disparity: Box::new(move |_, _| base),
            region: Box::new(|_, _| true),
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn right_image_is_the_left_shifted_by_the_disparity() {
        let tex = Texture::new(1);
        let layers = vec![Layer {
            disparity: Box::new(|_, _| 2.5),
            region: Box::new(|_, _| true),
        }];
        let pair = render(40, 10, tex, &layers, 0.0, 0.0);
        // right(x + 2.5) = left(x): right(12) = T(9.5).
        assert!((f64::from(pair.right.get(12, 5)) - tex.at(9.5, 5.0)).abs() < 1e-6);
        assert!(pair.visible[5 * 40 + 10]);
        assert!(!pair.visible[5 * 40 + 38]);
    }

    #[test]
    fn a_raised_band_occludes_the_plane_beside_it() {
        let pair = render(
            60,
            4,
            Texture::new(2),
            &raised_band(20.0, 30.0, 0.0, 6.0),
            0.0,
            0.0,
        );
        // Plane pixels 30..36 land on right 30..36, covered by the band (24..30 + 6).
        assert!(!pair.visible[2 * 60 + 32]);
        assert!(pair.visible[2 * 60 + 25]);
        assert!(pair.visible[2 * 60 + 40]);
    }
}
