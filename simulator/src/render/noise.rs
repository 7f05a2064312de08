//! Scan noise: the SE signal of a pixel is a count of electrons, so its
//! relative noise falls as 1/√(dwell).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::scene::noise::{gaussian, mix64, substream};

/// Detector noise.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `electrons_per_us` | 30 | detected electrons per µs of dwell at full signal: noise σ = √(signal / (electrons_per_us · dwell)) |
/// | `read_noise` | 0.003 | dwell-independent amplifier noise (σ, in output units) |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseParams {
    pub electrons_per_us: f64,
    pub read_noise: f64,
}

impl Default for NoiseParams {
    fn default() -> Self {
        Self {
            electrons_per_us: 30.0,
            read_noise: 0.003,
        }
    }
}

impl NoiseParams {
    /// No noise at all (clean renders for tests and ground-truth checks).
    #[must_use]
    pub fn none() -> Self {
        Self {
            electrons_per_us: f64::INFINITY,
            read_noise: 0.0,
        }
    }
}

/// Adds shot-like noise (Gaussian with the Poisson variance) to signals in
/// `[0, 1]` for a pixel dwell of `dwell_us`. Deterministic for a `seed`,
/// whatever the thread count.
pub fn add_scan_noise(pixels: &mut [f32], dwell_us: f64, params: &NoiseParams, seed: u64) {
    let electrons = params.electrons_per_us * dwell_us.max(1e-6);
    let stream = substream(seed, 0x5CA7);
    pixels
        .par_chunks_mut(4096)
        .enumerate()
        .for_each(|(chunk, px)| {
            for (k, v) in px.iter_mut().enumerate() {
                // Pixel index, for an independent deviate per pixel.
                let idx = (chunk * 4096 + k) as u64;
                let h = mix64(stream ^ idx.wrapping_mul(0x9E37_79B9_7F4A_7C15));
                let signal = f64::from(*v).max(0.0);
                let sigma = (signal / electrons + params.read_noise * params.read_noise).sqrt();
                #[allow(clippy::cast_possible_truncation)]
                {
                    *v = (signal + sigma * gaussian(h)) as f32;
                }
            }
        });
}
