//! The SIFT-flow energy, Liu, Yuen, Torralba (PAMI 2011) equation (10):
//!
//! ```text
//! E(w) = Σ_p min(‖s1(p) − s2(p + w(p))‖₁, t)                    data
//!      + Σ_p η (|u(p)| + |v(p)|)                                 small displacement
//!      + Σ_(p,q)∈ε min(α |u(p) − u(q)|, d) + min(α |v(p) − v(q)|, d)   smoothness
//! ```
//!
//! with `w = (u, v)` integer flow, `ε` the 4-neighbourhood. The reference code
//! calls η `gamma`; we keep that name. Each pixel's labels live in a window
//! `[−w, w]` around a per-pixel offset (coarse-to-fine initialisation), so the
//! flow is `offset + label − w`.

use rayon::prelude::*;

use crate::vision::dense::dense_sift::{DESCRIPTOR_LEN, DescriptorImage, L1Query};
use crate::vision::pages;

/// Parameters of eq. (10) at one pyramid level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnergyWeights {
    /// α: slope of the truncated L1 smoothness.
    pub alpha: f32,
    /// d: truncation of the smoothness.
    pub d: f32,
    /// η (γ in the reference code): weight of the small-displacement term.
    pub gamma: f32,
}

/// Per-edge truncation of the smoothness term, replacing
/// [`EnergyWeights::d`] on every edge of the grid: `right[p]` for the edge
/// between pixel `p` and `p + 1`, `down[p]` for `p` and `p + width` (the last
/// column's `right` and the last row's `down` are never read).
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeTruncation {
    pub right: Vec<f32>,
    pub down: Vec<f32>,
}

/// A contrast-sensitive [`EdgeTruncation`] from the source image of a level:
/// `tight + (d − tight) · exp(−(ΔI / (k · m))²)` on every edge, where ΔI is
/// the intensity difference across the edge and `m` its median over the
/// image. Edges across a strong intensity edge, where depth steps lie, get
/// the tight truncation; weakly textured surface keeps `d`.
#[must_use]
pub fn contrast_truncation(
    img: &super::super::Image,
    d: f32,
    tight: f32,
    k: f32,
) -> EdgeTruncation {
    let (w, h) = img.dimensions();
    let px = img.data();
    let diff = |p: usize, q: usize| (px[p] - px[q]).abs();
    let right: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|p| if p % w + 1 < w { diff(p, p + 1) } else { 0.0 })
        .collect();
    let down: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|p| if p / w + 1 < h { diff(p, p + w) } else { 0.0 })
        .collect();
    let m = median_positive(&right, &down).unwrap_or(1.0);
    let scale = (k * m).max(1e-12);
    let t = |v: f32| {
        let v = if v.is_finite() { v } else { 0.0 };
        tight + (d - tight) * (-(v / scale).powi(2)).exp()
    };
    EdgeTruncation {
        right: right.into_par_iter().map(t).collect(),
        down: down.into_par_iter().map(t).collect(),
    }
}

/// The element of rank `n / 2` (0-based, ascending) of the `n` finite positive values of `a`
/// and `b` together; `None` when there are none.
///
/// A positive finite `f32` orders as its bits: parallel counting passes over 11, 11 and 10 of
/// them, each among the values that share the digits found so far, find the same element as a
/// selection on a collected copy (serial, a few milliseconds a level).
fn median_positive(a: &[f32], b: &[f32]) -> Option<f32> {
    const CHUNK: usize = 1 << 16;
    const BINS: usize = 1 << 11;
    // (shift, digit mask) from the highest digit down.
    const DIGITS: [(u32, u32); 3] = [(21, 0x7FF), (10, 0x7FF), (0, 0x3FF)];
    let key = |v: f32| (v.is_finite() && v > 0.0).then(|| v.to_bits());
    // Counts of the digit at `shift` of the keys whose bits above it equal `prefix`.
    let count = |shift: u32, mask: u32, prefix: Option<u32>| -> Vec<u64> {
        let above = shift + mask.count_ones();
        a.par_chunks(CHUNK)
            .chain(b.par_chunks(CHUNK))
            .fold(
                || vec![0u64; BINS],
                |mut h, chunk| {
                    for &v in chunk {
                        if let Some(k) = key(v)
                            && prefix.is_none_or(|p| k >> above == p)
                        {
                            h[((k >> shift) & mask) as usize] += 1;
                        }
                    }
                    h
                },
            )
            .reduce(
                || vec![0u64; BINS],
                |mut x, y| {
                    for (p, q) in x.iter_mut().zip(&y) {
                        *p += q;
                    }
                    x
                },
            )
    };
    let mut prefix: Option<u32> = None;
    let mut rank = None;
    for (shift, mask) in DIGITS {
        let h = count(shift, mask, prefix);
        let mut r = match rank {
            Some(r) => r,
            None => {
                let n: u64 = h.iter().sum();
                if n == 0 {
                    return None;
                }
                n / 2
            }
        };
        // The digit whose bin holds rank `r`, and the rank within it.
        let mut digit = 0u32;
        for (d, &n) in h.iter().enumerate() {
            if r < n {
                // A bin index below 2^11.
                #[allow(clippy::cast_possible_truncation)]
                let d32 = d as u32;
                digit = d32;
                break;
            }
            r -= n;
        }
        rank = Some(r);
        prefix = Some((prefix.unwrap_or(0) << mask.count_ones()) | digit);
    }
    prefix.map(f32::from_bits)
}

/// Label geometry of one level: per-pixel offsets and uniform windows.
#[derive(Debug, Clone)]
pub struct LabelSpace {
    pub width: usize,
    pub height: usize,
    /// Per plane (0 = u, 1 = v): the half window `w`, states `2w + 1`.
    pub window: [usize; 2],
    /// Per plane: the offset of each pixel (row-major).
    pub offset: [Vec<i32>; 2],
}

impl LabelSpace {
    /// Number of states of plane `k`.
    #[must_use]
    pub fn states(&self, k: usize) -> usize {
        2 * self.window[k] + 1
    }

    /// The flow component of plane `k` at pixel `p` for label `l`.
    #[must_use]
    #[inline]
    pub fn flow(&self, k: usize, p: usize, l: usize) -> i32 {
        self.offset[k][p] + l as i32 - self.window[k] as i32
    }
}

/// The data term of eq. (10) for every pixel and label pair, `u16` per entry
/// (a descriptor L1 distance is at most 128 · 255 = 32 640).
///
/// Layout: `cost[(p · n_v + l_v) · n_u + l_u]`.
#[derive(Debug, Clone)]
pub struct DataTerm {
    pub cost: Vec<u16>,
    /// The energy counts `scale · cost` (1 at a pyramid level; `4^j` on the
    /// grids of the multigrid BP, which store the mean of `4^j` pixels).
    pub scale: f32,
    /// Cost given to matches that fall outside the second image (or on its
    /// invalid pixels): the median of the inside matches, as in the reference code.
    pub outside_cost: u16,
}

/// Marks a label whose match falls outside the second image during the first pass.
const OUTSIDE: u16 = u16::MAX;

impl DataTerm {
    /// Computes the data term of every label of `space`.
    ///
    /// `valid1` (row-major over `s1`) marks the pixels that have a data term:
    /// the others are not matched and cost 0 for every label (`None`: all
    /// have one). `valid2` (row-major over `s2`) marks pixels of the second
    /// image that may be matched; `truncation` is `t` of eq. (10) (`None`:
    /// not truncated, as the reference code runs).
    #[must_use]
    pub fn compute(
        s1: &DescriptorImage,
        s2: &DescriptorImage,
        space: &LabelSpace,
        valid1: Option<&[bool]>,
        valid2: Option<&[bool]>,
        truncation: Option<f32>,
    ) -> Self {
        let (w, h) = (space.width, space.height);
        let (nu, nv) = (space.states(0), space.states(1));
        let (w2, h2) = (s2.width() as i64, s2.height() as i64);
        let per_pixel = nu * nv;
        let mut cost = pages::zeroed::<u16>(w * h * per_pixel);
        let w2u = s2.width();
        let (wu, wv) = (space.window[0] as i64, space.window[1] as i64);
        cost.par_chunks_mut(w * per_pixel)
            .enumerate()
            .for_each(|(y, row)| {
                let (off_u, off_v) = (
                    &space.offset[0][y * w..(y + 1) * w],
                    &space.offset[1][y * w..(y + 1) * w],
                );
                for (x, out) in row.chunks_exact_mut(per_pixel).enumerate() {
                    let p = y * w + x;
                    if valid1.is_some_and(|m| !m[p]) {
                        // Left out of the median below; zero at the end.
                        out.fill(OUTSIDE);
                        continue;
                    }
                    let a = L1Query::new(s1.at(x, y));
                    // The match of labels (0, 0); label l adds l (`LabelSpace::flow`).
                    let x2_0 = x as i64 + i64::from(off_u[x]) - wu;
                    let y2_0 = y as i64 + i64::from(off_v[x]) - wv;
                    for (lv, out_v) in out.chunks_exact_mut(nu).enumerate() {
                        let y2 = y2_0 + lv as i64;
                        if y2 < 0 || y2 >= h2 {
                            out_v.fill(OUTSIDE);
                            continue;
                        }
                        // Inside the image: the cast is in range.
                        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                        let yy = y2 as usize;
                        let row2 = s2.row(yy);
                        let valid_row = valid2.map(|m| &m[yy * w2u..(yy + 1) * w2u]);
                        for (lu, o) in out_v.iter_mut().enumerate() {
                            let x2 = x2_0 + lu as i64;
                            *o = if x2 < 0 || x2 >= w2 {
                                OUTSIDE
                            } else {
                                // Inside the image: the cast is in range.
                                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                                let xx = x2 as usize;
                                if valid_row.is_some_and(|m| !m[xx]) {
                                    OUTSIDE
                                } else {
                                    let b = row2[xx * DESCRIPTOR_LEN..(xx + 1) * DESCRIPTOR_LEN]
                                        .try_into()
                                        .expect("DESCRIPTOR_LEN bytes");
                                    // At most 32 640: fits.
                                    #[allow(clippy::cast_possible_truncation)]
                                    let c = a.distance(b) as u16;
                                    c
                                }
                            };
                        }
                    }
                }
            });
        let outside_cost = median_inside(&cost);
        let cap = truncation.map_or(u16::MAX - 1, |t| {
            // Clamped into the u16 range first.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let c = t.clamp(0.0, f32::from(u16::MAX - 1)) as u16;
            c
        });
        cost.par_chunks_mut(per_pixel)
            .enumerate()
            .for_each(|(p, costs)| {
                if valid1.is_some_and(|m| !m[p]) {
                    costs.fill(0);
                    return;
                }
                for c in costs {
                    *c = if *c == OUTSIDE {
                        outside_cost.min(cap)
                    } else {
                        (*c).min(cap)
                    };
                }
            });
        Self {
            cost,
            scale: 1.0,
            outside_cost,
        }
    }

    /// The data term of the next coarser grid of the multigrid BP (Felzenszwalb
    /// & Huttenlocher 2006, as the reference code): a coarse node stands for
    /// 2 × 2 pixels and its cost is theirs summed, label by label (each child's
    /// label aligned through its own offset). Stored as the mean with `scale`
    /// multiplied by 4. Returns the coarse label space too.
    #[must_use]
    pub fn coarsen(&self, space: &LabelSpace) -> (LabelSpace, Self) {
        let (w, h) = (space.width, space.height);
        let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
        let (nu, nv) = (space.states(0), space.states(1));
        let per = nu * nv;
        let children = |cx: usize, cy: usize| {
            [(0, 0), (1, 0), (0, 1), (1, 1)]
                .into_iter()
                .map(move |(dx, dy)| (2 * cx + dx, 2 * cy + dy))
                .filter(move |&(x, y)| x < w && y < h)
                .map(move |(x, y)| y * w + x)
        };
        let mut offset = [vec![0i32; cw * ch], vec![0i32; cw * ch]];
        for (coarse, fine) in offset.iter_mut().zip(&space.offset) {
            // Row by row on every core (each mean its own: the same values).
            coarse.par_chunks_mut(cw).enumerate().for_each(|(cy, row)| {
                for (cx, o) in row.iter_mut().enumerate() {
                    let (sum, n) = children(cx, cy)
                        .fold((0i64, 0i64), |(s, n), p| (s + i64::from(fine[p]), n + 1));
                    // A mean of i32 offsets.
                    #[allow(clippy::cast_possible_truncation)]
                    let mean = (sum as f64 / n as f64).round() as i32;
                    *o = mean;
                }
            });
        }
        let coarse_space = LabelSpace {
            width: cw,
            height: ch,
            window: space.window,
            offset,
        };
        let mut cost = vec![0u16; cw * ch * per];
        cost.par_chunks_mut(cw * per)
            .enumerate()
            .for_each(|(cy, row)| {
                let mut acc = vec![0u32; per];
                let mut from_u = vec![0usize; nu];
                for cx in 0..cw {
                    let c = cy * cw + cx;
                    acc.fill(0);
                    let mut n = 0u32;
                    for p in children(cx, cy) {
                        let du = coarse_space.offset[0][c] - space.offset[0][p];
                        let dv = coarse_space.offset[1][c] - space.offset[1][p];
                        let src = self.pixel(p, per);
                        n += 1;
                        // Mostly the child's labels are the parent's: a plain sum.
                        if du == 0 && dv == 0 {
                            for (a, &s) in acc.iter_mut().zip(src) {
                                *a += u32::from(s);
                            }
                            continue;
                        }
                        for (lu, f) in from_u.iter_mut().enumerate() {
                            *f = clamp_label(lu, du, nu);
                        }
                        for (lv, a) in acc.chunks_exact_mut(nu).enumerate() {
                            let sv = clamp_label(lv, dv, nv);
                            let s = &src[sv * nu..(sv + 1) * nu];
                            for (a, &su) in a.iter_mut().zip(&from_u) {
                                *a += u32::from(s[su]);
                            }
                        }
                    }
                    for (o, &a) in row[cx * per..(cx + 1) * per].iter_mut().zip(&acc) {
                        // The mean of u16 values, rounded half up (a shift for 4 children).
                        #[allow(clippy::cast_possible_truncation)]
                        let m = if n == 4 {
                            (a + 2) >> 2
                        } else {
                            (a + n / 2) / n
                        } as u16;
                        *o = m;
                    }
                }
            });
        (
            coarse_space,
            Self {
                cost,
                scale: self.scale * 4.0,
                outside_cost: self.outside_cost,
            },
        )
    }

    /// The costs of pixel `p`, `[l_v][l_u]`.
    #[must_use]
    #[inline]
    pub fn pixel(&self, p: usize, per_pixel: usize) -> &[u16] {
        &self.cost[p * per_pixel..(p + 1) * per_pixel]
    }
}

/// Label `l + shift` clamped into `0..n`.
#[inline]
pub fn clamp_label(l: usize, shift: i32, n: usize) -> usize {
    let n_i = i32::try_from(n).unwrap_or(i32::MAX);
    // Clamped into 0..n.
    #[allow(clippy::cast_sign_loss)]
    let c = (l as i32 + shift).clamp(0, n_i - 1) as usize;
    c
}

/// Histograms [`median_inside`] counts into side by side, entry `i` into `i mod 4`, summed
/// after: neighbouring costs mostly fall into the same bin, whose increments would otherwise
/// wait for each other.
const HISTOGRAM_LANES: usize = 4;

/// The median of the entries that are not [`OUTSIDE`], to two units (`2i + 1` for the first
/// pair of values `2i, 2i + 1` at which half of them are counted); 0 when every match falls
/// outside.
///
/// In two passes over small histograms (the 256-value blocks `c >> 8`, then the pairs within
/// the block that holds the median) rather than one over all 32 768 pairs: both stay in the
/// first-level cache.
fn median_inside(cost: &[u16]) -> u16 {
    /// Bins `0..256` count the blocks of the inside entries, bin 256 the outside ones.
    fn blocks(chunk: &[u16], h: &mut [u64; 257]) {
        let bin = |c: u16| usize::from(c >> 8) + usize::from(c == OUTSIDE);
        let mut lanes = [[0u64; 257]; HISTOGRAM_LANES];
        let mut quads = chunk.chunks_exact(HISTOGRAM_LANES);
        for q in &mut quads {
            for (l, &c) in lanes.iter_mut().zip(q) {
                l[bin(c)] += 1;
            }
        }
        for &c in quads.remainder() {
            lanes[0][bin(c)] += 1;
        }
        for l in &lanes {
            for (a, &n) in h.iter_mut().zip(l) {
                *a += n;
            }
        }
    }
    /// The pairs `(c >> 1) & 127` of the inside entries of block `b`.
    fn pairs(chunk: &[u16], b: u16, h: &mut [u64; 128]) {
        let mut lanes = [[0u64; 128]; HISTOGRAM_LANES];
        let add = |l: &mut [u64; 128], c: u16| {
            let hit = (c >> 8 == b) & (c != OUTSIDE);
            l[usize::from((c >> 1) & 127)] += u64::from(hit);
        };
        let mut quads = chunk.chunks_exact(HISTOGRAM_LANES);
        for q in &mut quads {
            for (l, &c) in lanes.iter_mut().zip(q) {
                add(l, c);
            }
        }
        for &c in quads.remainder() {
            add(&mut lanes[0], c);
        }
        for l in &lanes {
            for (a, &n) in h.iter_mut().zip(l) {
                *a += n;
            }
        }
    }
    fn add<const N: usize>(mut a: [u64; N], b: [u64; N]) -> [u64; N] {
        for (x, y) in a.iter_mut().zip(b) {
            *x += y;
        }
        a
    }
    let coarse = cost
        .par_chunks(1 << 16)
        .fold(
            || [0u64; 257],
            |mut h, chunk| {
                blocks(chunk, &mut h);
                h
            },
        )
        .reduce(|| [0u64; 257], add);
    let total: u64 = coarse[..256].iter().sum();
    if total == 0 {
        return 0;
    }
    // The block where the count reaches half, and the count below it.
    let mut below = 0;
    let mut block = 0;
    for (b, &n) in coarse[..256].iter().enumerate() {
        if 2 * (below + n) >= total {
            block = b;
            break;
        }
        below += n;
    }
    // A block index below 256.
    #[allow(clippy::cast_possible_truncation)]
    let b = block as u16;
    let fine = cost
        .par_chunks(1 << 16)
        .fold(
            || [0u64; 128],
            |mut h, chunk| {
                pairs(chunk, b, &mut h);
                h
            },
        )
        .reduce(|| [0u64; 128], add);
    let mut acc = below;
    for (i, &n) in fine.iter().enumerate() {
        acc += n;
        if 2 * acc >= total {
            // The pair `128 b + i` < 2^15, so 2 (128 b + i) + 1 fits in u16.
            #[allow(clippy::cast_possible_truncation)]
            return (2 * (128 * usize::from(b) + i) + 1) as u16;
        }
    }
    unreachable!("the block holds the median")
}

/// Energy (10) of a labelling (`labels[k][p]`).
///
/// Row by row: the flows of a row and of the next are materialised first so
/// that the smoothness terms vectorise (this runs after every BP iteration).
#[must_use]
pub fn energy(
    data: &DataTerm,
    space: &LabelSpace,
    labels: &[Vec<u16>; 2],
    weights: &EnergyWeights,
) -> f64 {
    energy_with(data, space, labels, weights, None)
}

/// [`energy`] with the truncation of every edge from `edges` (`None`: `d`).
#[must_use]
pub fn energy_with(
    data: &DataTerm,
    space: &LabelSpace,
    labels: &[Vec<u16>; 2],
    weights: &EnergyWeights,
    edges: Option<&EdgeTruncation>,
) -> f64 {
    let (w, h) = (space.width, space.height);
    let (nu, nv) = (space.states(0), space.states(1));
    let per = nu * nv;
    let window = [space.window[0] as i32, space.window[1] as i32];
    let (alpha, d) = (weights.alpha, weights.d);
    let flows = |k: usize, y: usize, out: &mut [f32]| {
        let row = y * w..(y + 1) * w;
        for ((o, &off), &l) in out
            .iter_mut()
            .zip(&space.offset[k][row.clone()])
            .zip(&labels[k][row])
        {
            *o = (off + i32::from(l) - window[k]) as f32;
        }
    };
    let mut rows = Vec::with_capacity(h);
    (0..h)
        .into_par_iter()
        .map_init(
            || vec![0f32; 4 * w],
            |buf, y| {
                let (cur, next) = buf.split_at_mut(2 * w);
                let mut smooth = 0f32;
                let mut range = 0f32;
                for k in 0..2 {
                    let c = &mut cur[k * w..(k + 1) * w];
                    flows(k, y, c);
                    match edges {
                        None => {
                            for (a, b) in c.iter().zip(&c[1..]) {
                                smooth += (alpha * (a - b).abs()).min(d);
                            }
                        }
                        Some(e) => {
                            for ((a, b), &t) in c.iter().zip(&c[1..]).zip(&e.right[y * w..]) {
                                smooth += (alpha * (a - b).abs()).min(t);
                            }
                        }
                    }
                    range += c.iter().map(|f| f.abs()).sum::<f32>();
                    if y + 1 < h {
                        let n = &mut next[k * w..(k + 1) * w];
                        flows(k, y + 1, n);
                        match edges {
                            None => {
                                for (a, b) in c.iter().zip(n.iter()) {
                                    smooth += (alpha * (a - b).abs()).min(d);
                                }
                            }
                            Some(e) => {
                                for ((a, b), &t) in c.iter().zip(n.iter()).zip(&e.down[y * w..]) {
                                    smooth += (alpha * (a - b).abs()).min(t);
                                }
                            }
                        }
                    }
                }
                let mut data_sum = 0u64;
                let row = y * w;
                for (x, (&lu, &lv)) in labels[0][row..row + w]
                    .iter()
                    .zip(&labels[1][row..row + w])
                    .enumerate()
                {
                    let p = row + x;
                    data_sum +=
                        u64::from(data.cost[p * per + usize::from(lv) * nu + usize::from(lu)]);
                }
                f64::from(data.scale) * data_sum as f64
                    + f64::from(weights.gamma) * f64::from(range)
                    + f64::from(smooth)
            },
        )
        .collect_into_vec(&mut rows);
    // Rows summed in order: a parallel sum's order follows work stealing, and the reported
    // energy would change in its last bits from run to run.
    rows.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The median by its definition: one histogram over all pairs of values.
    fn median_by_definition(cost: &[u16]) -> u16 {
        let mut hist = vec![0u64; 1 << 15];
        for &c in cost.iter().filter(|&&c| c != OUTSIDE) {
            hist[usize::from(c >> 1)] += 1;
        }
        let total: u64 = hist.iter().sum();
        let mut acc = 0;
        for (i, &n) in hist.iter().enumerate() {
            acc += n;
            if 2 * acc >= total && total > 0 {
                return u16::try_from(2 * i + 1).unwrap();
            }
        }
        0
    }

    #[test]
    fn median_inside_equals_its_definition() {
        let mut s = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for (len, spread, outside) in [
            (0, 100, 0),
            (5, 100, 5),
            (1, 30_000, 0),
            (1000, 300, 10),
            (200_000, 32_641, 3),
            (150_000, 65_535, 2),
            (70_000, 2, 4),
        ] {
            let cost: Vec<u16> = (0..len)
                .map(|_| {
                    let r = next();
                    if outside > 0 && r % 10 < outside {
                        OUTSIDE
                    } else {
                        u16::try_from((r >> 20) % spread).unwrap()
                    }
                })
                .collect();
            assert_eq!(
                median_inside(&cost),
                median_by_definition(&cost),
                "{len} entries below {spread}"
            );
        }
    }

    /// The counting selection picks the element a selection on a collected copy picks.
    #[test]
    fn median_positive_is_the_selected_element() {
        let mut s = 0x853c_49e6_748f_ea9bu64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for (len_a, len_b) in [
            (0, 0),
            (1, 0),
            (0, 3),
            (10, 7),
            (70_000, 150_001),
            (4, 200_000),
        ] {
            let mut value = || match next() % 13 {
                0 => 0.0,
                1 => f32::NAN,
                2 => -1.5,
                3 => f32::INFINITY,
                4 => 0.25,
                r => (r as f32) * 1e-3 + (next() >> 40) as f32 * 1e-7,
            };
            let a: Vec<f32> = (0..len_a).map(|_| value()).collect();
            let b: Vec<f32> = (0..len_b).map(|_| value()).collect();
            let mut all: Vec<f32> = a
                .iter()
                .chain(&b)
                .copied()
                .filter(|v| v.is_finite() && *v > 0.0)
                .collect();
            let want = (!all.is_empty()).then(|| {
                let mid = all.len() / 2;
                *all.select_nth_unstable_by(mid, f32::total_cmp).1
            });
            let got = median_positive(&a, &b);
            assert_eq!(
                got.map(f32::to_bits),
                want.map(f32::to_bits),
                "{len_a} + {len_b}"
            );
        }
    }

    /// Edges across a strong intensity step get the tight truncation; the
    /// faint texture either side keeps most of `d`.
    #[test]
    fn contrast_truncation_is_tight_across_intensity_steps_only() {
        let (w, h) = (16, 6);
        let img = crate::vision::Image::from_fn(w, h, |x, y| {
            0.01 * ((x * 7 + y * 3) % 3) as f32 + if x >= 8 { 1.0 } else { 0.0 }
        });
        let (d, tight) = (1000.0, 100.0);
        let e = contrast_truncation(&img, d, tight, 2.0);
        for y in 0..h {
            for x in 0..w - 1 {
                let t = e.right[y * w + x];
                if x == 7 {
                    assert!(t < tight + 0.01 * (d - tight), "step edge ({x}, {y}): {t}");
                } else {
                    assert!(t > tight + 0.3 * (d - tight), "edge ({x}, {y}): {t}");
                }
            }
        }
        assert!(e.down.iter().all(|&t| t > tight + 0.3 * (d - tight)));
        // A flat image has no edge at all: `d` everywhere.
        let flat = contrast_truncation(&crate::vision::Image::filled(w, h, 0.5), d, tight, 2.0);
        assert!(flat.right.iter().chain(&flat.down).all(|&t| t == d));
    }

    #[test]
    fn energy_matches_a_direct_sum() {
        let (w, h) = (5, 4);
        let space = LabelSpace {
            width: w,
            height: h,
            window: [1, 1],
            offset: [
                (0..w * h).map(|p| (p % 3) as i32).collect(),
                vec![-1; w * h],
            ],
        };
        let cost: Vec<u16> = (0..w * h * 9).map(|i| (i * 13 % 50) as u16).collect();
        let data = DataTerm {
            cost,
            scale: 2.0,
            outside_cost: 0,
        };
        let labels = [
            (0..w * h).map(|p| (p % 3) as u16).collect::<Vec<_>>(),
            (0..w * h).map(|p| ((p / 2) % 3) as u16).collect::<Vec<_>>(),
        ];
        let wts = EnergyWeights {
            alpha: 3.0,
            d: 5.0,
            gamma: 0.5,
        };
        let mut want = 0f64;
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let (lu, lv) = (usize::from(labels[0][p]), usize::from(labels[1][p]));
                want += 2.0 * f64::from(data.cost[p * 9 + lv * 3 + lu]);
                for (k, lab) in labels.iter().enumerate() {
                    let f = space.flow(k, p, usize::from(lab[p]));
                    want += 0.5 * f64::from(f.abs());
                    for q in [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)]
                        .into_iter()
                        .flatten()
                    {
                        let g = space.flow(k, q, usize::from(lab[q]));
                        want += (3.0 * f64::from((f - g).abs())).min(5.0);
                    }
                }
            }
        }
        let got = energy(&data, &space, &labels, &wts);
        assert!((got - want).abs() < 1e-3, "{got} vs {want}");
    }

    /// The energy is the same to the last bit whatever the number of threads (report.json
    /// carries it): the rows' energies are summed in order, not in work-stealing order.
    #[test]
    fn energy_is_the_same_on_any_number_of_threads() {
        // Large costs at a scale of 0.1: the sum needs more than f64's 53 bits, so its order
        // shows in the last bits.
        let (w, h) = (64, 3000);
        let space = LabelSpace {
            width: w,
            height: h,
            window: [1, 1],
            offset: [vec![0; w * h], vec![0; w * h]],
        };
        let cost: Vec<u16> = (0..w * h * 9).map(|i| (i * 7919 % 65_521) as u16).collect();
        let data = DataTerm {
            cost,
            scale: 0.1,
            outside_cost: 0,
        };
        let labels = [
            (0..w * h).map(|p| (p * 5 % 3) as u16).collect::<Vec<_>>(),
            (0..w * h).map(|p| (p * 11 % 3) as u16).collect::<Vec<_>>(),
        ];
        let wts = EnergyWeights {
            alpha: 0.3,
            d: 0.7,
            gamma: 0.13,
        };
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| energy(&data, &space, &labels, &wts))
        };
        let one = on(1);
        for threads in [2, 3, 8, 1] {
            for _ in 0..5 {
                assert_eq!(on(threads).to_bits(), one.to_bits(), "{threads} threads");
            }
        }
    }

    #[test]
    fn pixels_without_a_data_term_cost_nothing_and_stay_out_of_the_median() {
        use crate::vision::Image;
        use crate::vision::dense::dense_sift::{DenseSiftParams, dense_sift};
        let (w, h) = (20, 12);
        let img = Image::from_vec(
            w,
            h,
            // Flat (zero descriptors, matches among them cost 0) where the
            // mask below leaves the data term out.
            (0..w * h)
                .map(|p| {
                    if p % w < 8 {
                        0.5
                    } else {
                        ((p * 7919 % 97) as f32 / 97.0).sin().abs()
                    }
                })
                .collect(),
        )
        .unwrap();
        let d = dense_sift(&img, &DenseSiftParams { cell_size: 1 });
        let space = LabelSpace {
            width: w,
            height: h,
            window: [3, 1],
            offset: [vec![0; w * h], vec![0; w * h]],
        };
        let valid1: Vec<bool> = (0..w * h).map(|p| p % w >= 6).collect();
        let all = DataTerm::compute(&d, &d, &space, None, None, None);
        let some = DataTerm::compute(&d, &d, &space, Some(&valid1), None, None);
        let per = space.states(0) * space.states(1);
        // The median of the matches inside, from the valid pixels only.
        let mut inside: Vec<u16> = Vec::new();
        for p in (0..w * h).filter(|&p| valid1[p]) {
            for lv in 0..space.states(1) {
                for lu in 0..space.states(0) {
                    let (x, y) = (
                        (p % w) as i64 + lu as i64 - 3,
                        (p / w) as i64 + lv as i64 - 1,
                    );
                    if x >= 0 && y >= 0 && x < w as i64 && y < h as i64 {
                        inside.push(all.cost[p * per + lv * space.states(0) + lu]);
                    }
                }
            }
        }
        inside.sort_unstable();
        let median = inside[inside.len() / 2];
        assert!(
            some.outside_cost.abs_diff(median) <= 1,
            "{} vs {median}",
            some.outside_cost
        );
        assert!(
            all.outside_cost + 1 < median,
            "the test's flat band must pull the median"
        );
        for (p, &valid) in valid1.iter().enumerate() {
            let c = &some.cost[p * per..(p + 1) * per];
            if valid {
                // Inside matches as without the mask; outside ones at the median.
                for (l, (&a, &b)) in c.iter().zip(&all.cost[p * per..(p + 1) * per]).enumerate() {
                    assert!(
                        a == b || a == some.outside_cost,
                        "pixel {p} label {l}: {a} vs {b}"
                    );
                }
            } else {
                assert!(c.iter().all(|&x| x == 0), "pixel {p} has a data term");
            }
        }
    }

    /// Every entry of the data term by its definition: the L1 distance of the descriptors at the
    /// pixel and at its match, `OUTSIDE` (then the median) beyond the second image or on its
    /// invalid pixels, 0 on the first image's invalid pixels; per-pixel offsets that reach past
    /// every side, a second image of another size.
    #[test]
    fn data_term_matches_its_definition() {
        use crate::vision::dense::dense_sift::{DenseSiftParams, dense_sift, l1_distance};
        let image = |w: usize, h: usize, seed: usize| {
            crate::vision::Image::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|p| ((p * 7919 + seed) % 101) as f32 / 101.0)
                    .collect(),
            )
            .unwrap()
        };
        let (w, h, w2, h2) = (23, 17, 19, 21);
        let d1 = dense_sift(&image(w, h, 3), &DenseSiftParams { cell_size: 1 });
        let d2 = dense_sift(&image(w2, h2, 11), &DenseSiftParams { cell_size: 1 });
        let space = LabelSpace {
            width: w,
            height: h,
            window: [3, 2],
            offset: [
                (0..w * h).map(|p| (p * 13 % 11) as i32 - 5).collect(),
                (0..w * h).map(|p| (p * 5 % 7) as i32 - 3).collect(),
            ],
        };
        let valid1: Vec<bool> = (0..w * h).map(|p| p % 9 != 4).collect();
        let valid2: Vec<bool> = (0..w2 * h2).map(|p| p % 7 != 2).collect();
        let (nu, nv) = (space.states(0), space.states(1));
        for (m1, m2) in [(None, None), (Some(&valid1[..]), Some(&valid2[..]))] {
            let data = DataTerm::compute(&d1, &d2, &space, m1, m2, None);
            for p in 0..w * h {
                let (x, y) = ((p % w) as i32, (p / w) as i32);
                for lv in 0..nv {
                    for lu in 0..nu {
                        let got = data.cost[(p * nv + lv) * nu + lu];
                        if m1.is_some_and(|m| !m[p]) {
                            assert_eq!(got, 0, "pixel {p}");
                            continue;
                        }
                        let (x2, y2) = (x + space.flow(0, p, lu), y + space.flow(1, p, lv));
                        let inside = (0..w2 as i32).contains(&x2) && (0..h2 as i32).contains(&y2);
                        let want = if inside && m2.is_none_or(|m| m[y2 as usize * w2 + x2 as usize])
                        {
                            l1_distance(d1.at(p % w, p / w), d2.at(x2 as usize, y2 as usize)) as u16
                        } else {
                            data.outside_cost
                        };
                        assert_eq!(got, want, "pixel {p} labels ({lu}, {lv})");
                    }
                }
            }
        }
    }
}
