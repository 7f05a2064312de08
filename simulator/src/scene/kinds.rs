//! The synthetic specimens: each a height function z(s, r) (µm, up towards the
//! beam) with a secondary-electron yield per point, built from a seed.
//!
//! Coordinates are specimen coordinates in µm: `s` along the stage tilt axis,
//! `r` across it, origin at the field centre, which lies on the tilt axis.

use super::noise::{fbm, hash2, mix64, substream, unit};
use super::{SceneKind, Texture};

/// A specimen surface that can be sampled anywhere in the field.
pub(crate) trait SurfaceModel: Sync {
    /// Height (µm) and SE yield (0–1) of the surface at `(s, r)`.
    fn sample(&self, s: f64, r: f64) -> (f64, f64);
}

/// Seeded uniform deviates, one stream per use.
struct Draw {
    state: u64,
}

impl Draw {
    fn new(seed: u64, tag: u64) -> Self {
        Self {
            state: substream(seed, tag),
        }
    }

    fn next(&mut self) -> f64 {
        self.state = mix64(self.state);
        unit(self.state)
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

/// Builds the model of `kind` for a square field of side `field_um`.
pub(crate) fn build(kind: SceneKind, seed: u64, field_um: f64) -> (Box<dyn SurfaceModel>, Texture) {
    match kind {
        SceneKind::Particles => (
            Box::new(Particles::new(seed, field_um)),
            Texture {
                mottle: 0.22,
                mottle_lambda_um: 3.0,
                grain_um: 2.0,
                grain_contrast: 0.18,
                boundary_contrast: 0.25,
                speck_cell_um: 2.0,
                speck_brightness: 0.8,
                plain_below_yield: 0.0,
            },
        ),
        SceneKind::Grid => (
            Box::new(Grid::new(seed, field_um)),
            Texture {
                mottle: 0.18,
                mottle_lambda_um: 2.5,
                grain_um: 3.0,
                grain_contrast: 0.15,
                boundary_contrast: 0.25,
                speck_cell_um: 2.5,
                speck_brightness: 0.7,
                plain_below_yield: 0.0,
            },
        ),
        SceneKind::Rough => (
            Box::new(Rough::new(seed, field_um)),
            Texture {
                mottle: 0.2,
                mottle_lambda_um: 2.0,
                grain_um: 1.5,
                grain_contrast: 0.1,
                boundary_contrast: 0.2,
                speck_cell_um: 3.0,
                speck_brightness: 0.6,
                plain_below_yield: 0.0,
            },
        ),
        SceneKind::Dome => (
            Box::new(Dome::new(seed, field_um)),
            Texture {
                mottle: 0.2,
                mottle_lambda_um: 3.0,
                grain_um: 2.5,
                grain_contrast: 0.12,
                boundary_contrast: 0.25,
                speck_cell_um: 2.0,
                speck_brightness: 0.8,
                plain_below_yield: 0.0,
            },
        ),
        SceneKind::Bare => (
            Box::new(Particles::on_flat_support(seed, field_um)),
            Texture {
                plain_below_yield: 0.4,
                ..build(SceneKind::Particles, seed, field_um).1
            },
        ),
        SceneKind::Calgrid => (
            Box::new(CalGrid::new(seed)),
            Texture {
                mottle: 0.05,
                mottle_lambda_um: 2.0,
                grain_um: 3.0,
                grain_contrast: 0.04,
                boundary_contrast: 0.05,
                speck_cell_um: 4.0,
                speck_brightness: 0.1,
                plain_below_yield: 0.4,
            },
        ),
        SceneKind::Metal => (
            Box::new(Rough::new(seed, field_um)),
            Texture {
                mottle: 0.04,
                mottle_lambda_um: 2.0,
                grain_um: 1.5,
                grain_contrast: 0.03,
                boundary_contrast: 0.04,
                speck_cell_um: 3.0,
                speck_brightness: 0.1,
                plain_below_yield: 0.0,
            },
        ),
    }
}

/// A gently undulating substrate (carbon tape, stub): low yield, sub-µm relief.
fn substrate(seed: u64, s: f64, r: f64, amplitude_um: f64) -> f64 {
    amplitude_um * fbm(substream(seed, 901), s, r, 25.0, 5, 0.5, 0.0)
}

const SUBSTRATE_YIELD: f64 = 0.32;

// ---------------------------------------------------------------- particles

#[derive(Clone, Copy)]
struct Particle {
    s: f64,
    r: f64,
    /// Semi-axes along the particle's own axes, µm.
    a: f64,
    b: f64,
    cos: f64,
    sin: f64,
    /// Height above the substrate, µm.
    c: f64,
    /// Faceted (a truncated pyramid) rather than a rounded grain.
    faceted: bool,
    yld: f64,
}

impl Particle {
    /// Height above the substrate at `(s, r)`, if the particle covers it.
    fn height(&self, s: f64, r: f64) -> Option<f64> {
        let (ds, dr) = (s - self.s, r - self.r);
        let u = (ds * self.cos + dr * self.sin) / self.a;
        let v = (-ds * self.sin + dr * self.cos) / self.b;
        if self.faceted {
            let m = u.abs().max(v.abs());
            // Steep sides (slope 4c per unit radius) up to a flat top.
            (m < 1.0).then(|| self.c * (4.0 * (1.0 - m)).min(1.0))
        } else {
            let q = u * u + v * v;
            (q < 1.0).then(|| self.c * (1.0 - q).sqrt())
        }
    }
}

/// Grains and particles of three size classes on a substrate.
struct Particles {
    seed: u64,
    /// Relief of the support, µm (0: flat).
    support_um: f64,
    particles: Vec<Particle>,
    /// Bucket grid over the field: indices of the particles touching each bucket.
    buckets: Vec<Vec<u32>>,
    bucket_um: f64,
    n_buckets: usize,
    half: f64,
}

impl Particles {
    fn new(seed: u64, field_um: f64) -> Self {
        let half = field_um / 2.0;
        let area = field_um * field_um;
        let mut draw = Draw::new(seed, 1);
        let mut particles = Vec::new();
        // (number per µm², semi-axis range µm, height/semi-axis range)
        let classes = [
            (0.000_5, 5.0, 12.0, 0.6, 1.3),
            (0.004, 1.5, 3.5, 0.5, 1.0),
            (0.015, 0.4, 1.0, 0.4, 0.9),
        ];
        for (density, amin, amax, cmin, cmax) in classes {
            // Counts are small positive numbers.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let n = (density * area).round().max(1.0) as usize;
            for _ in 0..n {
                let a = draw.range(amin, amax);
                let b = a * draw.range(0.55, 1.0);
                let angle = draw.range(0.0, std::f64::consts::PI);
                particles.push(Particle {
                    s: draw.range(-half, half),
                    r: draw.range(-half, half),
                    a,
                    b,
                    cos: angle.cos(),
                    sin: angle.sin(),
                    c: a * draw.range(cmin, cmax),
                    faceted: draw.next() < 0.3,
                    yld: draw.range(0.5, 0.95),
                });
            }
        }
        let bucket_um = 8.0;
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let n_buckets = (field_um / bucket_um).ceil().max(1.0) as usize;
        let mut buckets = vec![Vec::new(); n_buckets * n_buckets];
        let clamp_index = |x: f64| -> usize {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let k = ((x + half) / bucket_um).floor().max(0.0) as usize;
            k.min(n_buckets - 1)
        };
        for (k, p) in particles.iter().enumerate() {
            let reach = p.a.max(p.b);
            for bj in clamp_index(p.r - reach)..=clamp_index(p.r + reach) {
                for bi in clamp_index(p.s - reach)..=clamp_index(p.s + reach) {
                    #[allow(clippy::cast_possible_truncation)]
                    buckets[bj * n_buckets + bi].push(k as u32);
                }
            }
        }
        Self {
            seed,
            support_um: 0.4,
            particles,
            buckets,
            bucket_um,
            n_buckets,
            half,
        }
    }
}

impl Particles {
    /// The same particles on a flat support (z = 0).
    fn on_flat_support(seed: u64, field_um: f64) -> Self {
        Self {
            support_um: 0.0,
            ..Self::new(seed, field_um)
        }
    }

    /// The tallest particle over `(s, r)`: its height above the substrate and its yield.
    fn bump(&self, s: f64, r: f64) -> Option<(f64, f64)> {
        let bi = (s + self.half) / self.bucket_um;
        let bj = (r + self.half) / self.bucket_um;
        #[allow(clippy::cast_precision_loss)]
        let nb = self.n_buckets as f64;
        if bi < 0.0 || bj < 0.0 || bi >= nb || bj >= nb {
            return None;
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let idx = bj as usize * self.n_buckets + bi as usize;
        let mut best: Option<(f64, f64)> = None;
        for &k in &self.buckets[idx] {
            let p = &self.particles[k as usize];
            if let Some(h) = p.height(s, r)
                && best.is_none_or(|(bh, _)| h > bh)
            {
                best = Some((h, p.yld));
            }
        }
        best
    }
}

impl SurfaceModel for Particles {
    fn sample(&self, s: f64, r: f64) -> (f64, f64) {
        let base = substrate(self.seed, s, r, self.support_um);
        match self.bump(s, r) {
            Some((h, y)) if h > 0.0 => (base + h, y),
            _ => (base, SUBSTRATE_YIELD),
        }
    }
}

// ---------------------------------------------------------------- grid

/// A metal TEM grid (square mesh) lying on a substrate: flat-topped bars with
/// near-vertical walls and rounded top edges, repetitive square openings.
struct Grid {
    seed: u64,
    pitch: f64,
    half_bar: f64,
    thickness: f64,
    round_um: f64,
    cos: f64,
    sin: f64,
    offset: (f64, f64),
}

impl Grid {
    fn new(seed: u64, _field_um: f64) -> Self {
        let mut draw = Draw::new(seed, 2);
        let angle = draw.range(12.0, 30.0).to_radians();
        let pitch = draw.range(32.0, 40.0);
        Self {
            seed,
            pitch,
            half_bar: draw.range(4.0, 5.5),
            thickness: draw.range(14.0, 18.0),
            round_um: 1.5,
            cos: angle.cos(),
            sin: angle.sin(),
            offset: (draw.range(0.0, pitch), draw.range(0.0, pitch)),
        }
    }

    /// Distance (µm) from `x` inward into the nearest bar of a 1-D comb; negative in an opening.
    fn depth_into_bar(&self, x: f64) -> f64 {
        let m = x.rem_euclid(self.pitch);
        let d_centre = m.min(self.pitch - m);
        self.half_bar - d_centre
    }
}

impl SurfaceModel for Grid {
    fn sample(&self, s: f64, r: f64) -> (f64, f64) {
        let u = s * self.cos + r * self.sin + self.offset.0;
        let v = -s * self.sin + r * self.cos + self.offset.1;
        let d = self.depth_into_bar(u).max(self.depth_into_bar(v));
        let floor = substrate(self.seed, s, r, 0.35);
        if d <= 0.0 {
            return (floor, SUBSTRATE_YIELD);
        }
        // Vertical wall at the bar edge, then a rounded (convex) top edge.
        let rise = (d / self.round_um).min(1.0).sqrt();
        let polish = 0.06 * fbm(substream(self.seed, 902), s, r, 6.0, 4, 0.5, 0.0);
        (floor.max(self.thickness * rise + polish * rise), 0.72)
    }
}

// ---------------------------------------------------------------- calibration grid

/// A calibration grid: a square mesh of thin bars, about 2 µm high with steep walls, on a
/// flat, dark floor of low yield.
struct CalGrid {
    pitch: f64,
    half_bar: f64,
    height: f64,
    round_um: f64,
    cos: f64,
    sin: f64,
    offset: (f64, f64),
}

impl CalGrid {
    fn new(seed: u64) -> Self {
        let mut draw = Draw::new(seed, 5);
        let angle = draw.range(5.0, 20.0).to_radians();
        let pitch = draw.range(18.0, 22.0);
        Self {
            pitch,
            half_bar: draw.range(0.9, 1.2),
            height: draw.range(1.8, 2.4),
            round_um: 0.3,
            cos: angle.cos(),
            sin: angle.sin(),
            offset: (draw.range(0.0, pitch), draw.range(0.0, pitch)),
        }
    }

    fn depth_into_bar(&self, x: f64) -> f64 {
        let m = x.rem_euclid(self.pitch);
        self.half_bar - m.min(self.pitch - m)
    }
}

/// Yield of the calibration grid's floor: darker than the usual substrate.
const DARK_FLOOR_YIELD: f64 = 0.18;

impl SurfaceModel for CalGrid {
    fn sample(&self, s: f64, r: f64) -> (f64, f64) {
        let u = s * self.cos + r * self.sin + self.offset.0;
        let v = -s * self.sin + r * self.cos + self.offset.1;
        let d = self.depth_into_bar(u).max(self.depth_into_bar(v));
        if d <= 0.0 {
            return (0.0, DARK_FLOOR_YIELD);
        }
        (self.height * (d / self.round_um).min(1.0).sqrt(), 0.62)
    }
}

// ---------------------------------------------------------------- rough

#[derive(Clone, Copy)]
struct Scratch {
    s: f64,
    r: f64,
    cos: f64,
    sin: f64,
    depth: f64,
    width: f64,
}

/// A machined surface: periodic tool (feed) marks with a wandering phase,
/// fractal roughness, waviness and a few scratches.
struct Rough {
    seed: u64,
    cos: f64,
    sin: f64,
    feed_um: f64,
    cusp_um: f64,
    scratches: Vec<Scratch>,
}

impl Rough {
    fn new(seed: u64, field_um: f64) -> Self {
        let mut draw = Draw::new(seed, 3);
        let angle = draw.range(0.0, std::f64::consts::PI);
        let half = field_um / 2.0;
        let scratches = (0..6)
            .map(|_| {
                let a = draw.range(0.0, std::f64::consts::PI);
                Scratch {
                    s: draw.range(-half, half),
                    r: draw.range(-half, half),
                    cos: a.cos(),
                    sin: a.sin(),
                    depth: draw.range(0.5, 1.5),
                    width: draw.range(0.4, 1.2),
                }
            })
            .collect();
        Self {
            seed,
            cos: angle.cos(),
            sin: angle.sin(),
            feed_um: draw.range(9.0, 14.0),
            cusp_um: draw.range(1.8, 2.6),
            scratches,
        }
    }
}

impl SurfaceModel for Rough {
    fn sample(&self, s: f64, r: f64) -> (f64, f64) {
        let u = s * self.cos + r * self.sin;
        let v = -s * self.sin + r * self.cos;
        // Feed marks: parabolic cusps whose phase wanders along the mark (chatter).
        let wander = 0.15 * fbm(substream(self.seed, 903), v, 0.0, 40.0, 3, 0.5, 0.0);
        let f = (u / self.feed_um + wander).rem_euclid(1.0) - 0.5;
        let cusp = self.cusp_um * (4.0 * f * f - 1.0 / 3.0);
        let roughness = 0.9 * fbm(substream(self.seed, 904), s, r, 20.0, 7, 0.72, 0.0);
        let waviness = 2.0 * fbm(substream(self.seed, 905), s, r, 120.0, 2, 0.5, 0.0);
        let mut z = cusp + roughness + waviness;
        for k in &self.scratches {
            let d = -(s - k.s) * k.sin + (r - k.r) * k.cos;
            let q = d / k.width;
            z -= k.depth * (-q * q).exp();
        }
        // Patches of oxide: yield varies slowly.
        let y = 0.55 + 0.08 * fbm(substream(self.seed, 906), s, r, 35.0, 2, 0.5, 0.0);
        (z, y)
    }
}

// ---------------------------------------------------------------- dome

/// A large dome (spherical cap) with a dent in its flank, dust on it, on a substrate.
struct Dome {
    seed: u64,
    centre: (f64, f64),
    radius: f64,
    height: f64,
    sphere: f64,
    dent: (f64, f64),
    dent_sigma: f64,
    dent_depth: f64,
    dust: Particles,
}

impl Dome {
    fn new(seed: u64, field_um: f64) -> Self {
        let mut draw = Draw::new(seed, 4);
        let radius = 0.32 * field_um;
        let height = draw.range(24.0, 30.0).min(0.9 * radius);
        let centre = (
            draw.range(-0.05, 0.05) * field_um,
            draw.range(-0.05, 0.05) * field_um,
        );
        let dir = draw.range(0.0, std::f64::consts::TAU);
        let dent_at = 0.45 * radius;
        let mut dust = Particles::new(mix64(seed ^ 0xD05E), field_um);
        // Only the small and medium classes: the big ones would hide the dome.
        dust.particles.iter_mut().for_each(|p| {
            if p.a > 4.0 {
                p.c = 0.0;
            }
        });
        Self {
            seed,
            centre,
            radius,
            height,
            sphere: (radius * radius + height * height) / (2.0 * height),
            dent: (
                centre.0 + dent_at * dir.cos(),
                centre.1 + dent_at * dir.sin(),
            ),
            dent_sigma: 0.15 * radius,
            dent_depth: draw.range(5.0, 8.0),
            dust,
        }
    }
}

impl SurfaceModel for Dome {
    fn sample(&self, s: f64, r: f64) -> (f64, f64) {
        let (ds, dr) = (s - self.centre.0, r - self.centre.1);
        let d2 = ds * ds + dr * dr;
        let base = substrate(self.seed, s, r, 0.3);
        let cap = if d2 < self.radius * self.radius {
            (self.sphere * self.sphere - d2).sqrt() - (self.sphere - self.height)
        } else {
            f64::NEG_INFINITY
        };
        let (es, er) = (s - self.dent.0, r - self.dent.1);
        let dent = self.dent_depth
            * (-(es * es + er * er) / (2.0 * self.dent_sigma * self.dent_sigma)).exp();
        let dome = cap - dent + 0.08 * fbm(substream(self.seed, 907), s, r, 8.0, 4, 0.5, 0.0);
        // A fillet where the dome meets the substrate: smooth maximum over ~1 µm.
        let k = 1.0;
        let surface = if dome > base {
            let h = (0.5 + 0.5 * (dome - base) / k).clamp(0.0, 1.0);
            dome * h + base * (1.0 - h) + k * h * (1.0 - h) * 0.5
        } else {
            base
        };
        let yld = if dome > base { 0.6 } else { SUBSTRATE_YIELD };
        // Dust: small particles resting on whatever is beneath them.
        match self.dust.bump(s, r) {
            Some((h, y)) if h > 0.0 => (surface + h, y),
            _ => (surface, yld),
        }
    }
}

/// Brightness variation of the material itself (albedo), evaluated at the exact
/// specimen point so both views of a point agree; `footprint` (µm) band-limits it.
///
/// Grains (crystallites with dark boundaries) show on bright, metallic
/// materials (`yld` above ~0.45), not on the low-yield substrate.
pub(crate) fn albedo(tex: &Texture, seed: u64, s: f64, r: f64, footprint: f64, yld: f64) -> f64 {
    use super::noise::{cellular, lod_weight};
    if yld < tex.plain_below_yield {
        return 1.0;
    }
    // Non-metallic materials (substrate, carbon) look grainy: stronger mottling.
    let metal = ((yld - 0.4) / 0.15).clamp(0.0, 1.0);
    let mottle = tex.mottle
        * (2.5 - 1.5 * metal)
        * fbm(
            substream(seed, 910),
            s,
            r,
            tex.mottle_lambda_um,
            5,
            0.7,
            footprint,
        );
    // Grains: per-grain brightness (channelling contrast) and dark boundaries.
    let (grain, boundary) = if metal > 0.0 {
        let (f1, f2, id) = cellular(substream(seed, 911), s / tex.grain_um, r / tex.grain_um);
        let grain_w = lod_weight(tex.grain_um, footprint);
        let grain = tex.grain_contrast * grain_w * (unit(id) - 0.5) * 2.0;
        let line_um = 0.08_f64;
        let eff = line_um.max(0.5 * footprint);
        let gap = (f2 - f1) * tex.grain_um;
        let boundary = tex.boundary_contrast * (line_um / eff) * (-(gap / eff).powi(2)).exp();
        (metal * grain, metal * boundary)
    } else {
        (0.0, 0.0)
    };
    // Specks of dust: small Gaussian spots, widened (and dimmed) to the
    // footprint. One candidate per cell, kept away from the cell's border, so
    // only the 2 × 2 cells nearest the point can reach it.
    let cs = s / tex.speck_cell_um - 0.5;
    let cr = r / tex.speck_cell_um - 0.5;
    let (ci, cj) = (cs.floor(), cr.floor());
    let stream = substream(seed, 912);
    let mut speck = 0.0;
    for dj in 0..=1 {
        for di in 0..=1 {
            #[allow(clippy::cast_possible_truncation)]
            let (ii, jj) = (ci as i64 + di, cj as i64 + dj);
            let h = hash2(stream, ii, jj);
            if (h & 0xFF) > 153 {
                continue;
            }
            #[allow(clippy::cast_precision_loss)]
            let ps =
                (ii as f64 + 0.25 + 0.5 * f64::from((h >> 8) as u16) / 65536.0) * tex.speck_cell_um;
            #[allow(clippy::cast_precision_loss)]
            let pr = (jj as f64 + 0.25 + 0.5 * f64::from((h >> 24) as u16) / 65536.0)
                * tex.speck_cell_um;
            let sigma = 0.08 + 0.2 * f64::from((h >> 40) as u16) / 65536.0;
            let var = sigma * sigma + 0.25 * footprint * footprint;
            let d2 = (s - ps).powi(2) + (r - pr).powi(2);
            if d2 > 12.0 * var {
                continue;
            }
            let sign = if (h >> 56) < 192 { 1.0 } else { -0.6 };
            speck +=
                sign * tex.speck_brightness * (sigma * sigma / var) * (-d2 / (2.0 * var)).exp();
        }
    }
    ((1.0 + mottle + grain - boundary) * (1.0 + speck)).max(0.05)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_has_walls_of_the_bar_thickness() {
        let g = Grid::new(5, 200.0);
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for k in 0..2000 {
            let x = f64::from(k) * 0.05;
            let (z, _) = g.sample(x, 0.3 * x);
            lo = lo.min(z);
            hi = hi.max(z);
        }
        assert!(hi - lo > 13.0 && hi - lo < 20.0, "relief {lo}..{hi}");
    }

    #[test]
    fn featureless_supports_are_flat_and_plain() {
        for kind in [SceneKind::Bare, SceneKind::Calgrid] {
            let (model, tex) = build(kind, 3, 200.0);
            let (mut floor, mut raised) = (0, 0);
            for k in 0..4000 {
                let (s, r) = (
                    f64::from(k % 80) * 1.3 - 50.0,
                    f64::from(k / 80) * 1.7 - 40.0,
                );
                let (z, y) = model.sample(s, r);
                if y < tex.plain_below_yield {
                    floor += 1;
                    assert_eq!(z, 0.0, "{kind}: the support is flat");
                    assert_eq!(albedo(&tex, 3, s, r, 0.1, y), 1.0, "{kind}: and plain");
                } else {
                    raised += 1;
                    assert!(z > 0.0, "{kind}");
                }
            }
            assert!(
                floor > 1000 && raised > 40,
                "{kind}: {floor} floor, {raised} raised"
            );
        }
    }

    #[test]
    fn particles_stand_above_substrate() {
        let p = Particles::new(3, 200.0);
        let max = (0..400)
            .flat_map(|j| {
                (0..400).map(move |i| (f64::from(i) * 0.5 - 100.0, f64::from(j) * 0.5 - 100.0))
            })
            .map(|(s, r)| p.sample(s, r).0)
            .fold(f64::NEG_INFINITY, f64::max);
        assert!(max > 4.0 && max < 20.0, "max {max}");
    }

    #[test]
    fn dome_is_about_thirty_microns_high() {
        let d = Dome::new(2, 200.0);
        let (top, _) = d.sample(d.centre.0, d.centre.1);
        let (edge, _) = d.sample(95.0, 95.0);
        assert!(top - edge > 20.0 && top - edge < 32.0, "{top} {edge}");
    }

    #[test]
    fn albedo_is_positive_and_textured() {
        let tex = build(SceneKind::Particles, 1, 100.0).1;
        let vals: Vec<f64> = (0..200)
            .map(|k| albedo(&tex, 1, f64::from(k) * 0.1, 0.0, 0.1, 0.7))
            .collect();
        assert!(vals.iter().all(|&v| v > 0.0));
        let mean = vals.iter().sum::<f64>() / 200.0;
        let sd = (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 200.0).sqrt();
        assert!(sd > 0.05, "texture too weak: sd {sd}");
    }
}
