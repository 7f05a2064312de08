//! Dual-layer loopy belief propagation with the sequential schedule (BP-S).
//!
//! Liu et al. (PAMI 2011, §3.2, Fig. 4) decouple the horizontal flow `u` and
//! the vertical flow `v` into two layers of the same grid: the smoothness of
//! eq. (10) acts within a layer, the data term couples the two nodes of a
//! pixel. Messages are min-sum; a message between neighbours of one layer is
//! computed with the distance transform of Felzenszwalb & Huttenlocher
//! (two passes for the L1 slope `α`, then the truncation `d`), in O(n) for `n`
//! states instead of O(n²). The inter-layer message costs O(n_u · n_v).
//!
//! Schedule (as the reference code): iteration `c` updates layer `c mod 2`,
//! sweeping forward in raster order (messages to the right and down) when
//! `c mod 4 < 2`, backward otherwise (left and up); the inter-layer messages
//! are updated on the first four iterations of every eight.
//!
//! Parallelism: the rows are cut into horizontal strips that sweep at the same
//! time; within a strip the order is exactly BP-S, a message that crosses a
//! strip boundary arrives one iteration later. With one strip this is the
//! sequential algorithm; the strip count depends only on the image height, so
//! results do not depend on the number of threads.

use rayon::prelude::*;

use super::energy::{DataTerm, EnergyWeights, LabelSpace, clamp_label, energy};

/// Incoming message slots of a node: from the left, right, upper, lower
/// neighbour on the same layer, and from the other layer.
const FROM_LEFT: usize = 0;
const FROM_RIGHT: usize = 1;
const FROM_UP: usize = 2;
const FROM_DOWN: usize = 3;
const FROM_DUAL: usize = 4;
const SLOTS: usize = 5;

/// Largest number of states of one layer (a half window of 63).
pub const MAX_STATES: usize = 127;

/// Min-sum loopy BP on the dual-layer graph of one pyramid level.
pub struct DualLayerBp<'a> {
    space: &'a LabelSpace,
    data: &'a DataTerm,
    weights: EnergyWeights,
    /// Per layer: `msgs[k][(p · SLOTS + slot) · n_k + l]`.
    msgs: [Vec<f32>; 2],
    strips: Vec<(usize, usize)>,
    min_strip_rows: usize,
    max_strips: usize,
}

/// What [`DualLayerBp::run`] returns.
#[derive(Debug, Clone)]
pub struct BpOutcome {
    /// The label of every pixel per layer (argmin of the beliefs).
    pub labels: [Vec<u16>; 2],
    /// Energy (10) after each iteration (the paper's Fig. 8).
    pub energy: Vec<f64>,
}

/// Splits `v` into consecutive mutable row blocks, one per strip.
fn split_strips<'b>(
    mut v: &'b mut [f32],
    strips: &[(usize, usize)],
    row_len: usize,
) -> Vec<&'b mut [f32]> {
    let mut out = Vec::with_capacity(strips.len());
    for &(y0, y1) in strips {
        let (a, b) = std::mem::take(&mut v).split_at_mut((y1 - y0) * row_len);
        out.push(a);
        v = b;
    }
    out
}

/// Strips of at least `min_rows` rows, at most `max_strips` of them.
fn strips_for(height: usize, min_rows: usize, max_strips: usize) -> Vec<(usize, usize)> {
    let n = (height / min_rows.max(1)).clamp(1, max_strips.max(1));
    (0..n)
        .map(|i| (i * height / n, (i + 1) * height / n))
        .filter(|(a, b)| b > a)
        .collect()
}

/// The message from a node with cost `h` (over its `n` labels) to a
/// neighbour whose offset is `shift` labels further: distance transform with
/// slope `s`, truncation at `min h + d`, normalised to a zero minimum.
#[inline]
fn spatial_message(h: &mut [f32], shift: i32, s: f32, d: f32, out: &mut [f32]) {
    let n = h.len();
    let cap = h.iter().copied().fold(f32::INFINITY, f32::min) + d;
    for l in 1..n {
        h[l] = h[l].min(h[l - 1] + s);
    }
    for l in (0..n - 1).rev() {
        h[l] = h[l].min(h[l + 1] + s);
    }
    let n_i = n as i32;
    let mut min = f32::INFINITY;
    for (l1, o) in out.iter_mut().enumerate() {
        let lp = l1 as i32 + shift;
        let v = if lp < 0 {
            h[0] + s * (-lp) as f32
        } else if lp >= n_i {
            h[n - 1] + s * (lp - n_i + 1) as f32
        } else {
            h[lp as usize]
        };
        let v = v.min(cap);
        min = min.min(v);
        *o = v;
    }
    for o in out.iter_mut() {
        *o -= min;
    }
}

/// The message from layer `k` to the other layer of the same pixel:
/// `m(l') = min_l h(l) + scale · D(l, l')`, normalised. `cost` is `[l_v][l_u]`.
#[inline]
fn dual_message(k: usize, h: &[f32], cost: &[u16], scale: f32, nu: usize, out: &mut [f32]) {
    if k == 0 {
        // u → v: for every l_v, min over l_u (contiguous).
        for (o, row) in out.iter_mut().zip(cost.chunks_exact(nu)) {
            *o = row
                .iter()
                .zip(h)
                .map(|(&c, &a)| a + scale * f32::from(c))
                .fold(f32::INFINITY, f32::min);
        }
    } else {
        // v → u: running minimum over l_v, vectorised along l_u.
        out.fill(f32::INFINITY);
        for (&a, row) in h.iter().zip(cost.chunks_exact(nu)) {
            for (o, &c) in out.iter_mut().zip(row) {
                *o = o.min(a + scale * f32::from(c));
            }
        }
    }
    let min = out.iter().copied().fold(f32::INFINITY, f32::min);
    for o in out.iter_mut() {
        *o -= min;
    }
}

struct Sweep<'c> {
    space: &'c LabelSpace,
    data: &'c DataTerm,
    weights: EnergyWeights,
    k: usize,
    forward: bool,
    dual: bool,
}

impl Sweep<'_> {
    /// Sweeps the rows `y0..y1` of layer `k`. `mk` holds those rows of layer
    /// `k`, `mo` of the other layer. Returns the messages that leave the strip
    /// (downwards from its last row or upwards from its first), one per column.
    fn strip(&self, y0: usize, y1: usize, mk: &mut [f32], mo: &mut [f32]) -> Vec<f32> {
        let sp = self.space;
        let (w, h) = (sp.width, sp.height);
        let k = self.k;
        let n = sp.states(k);
        let no = sp.states(1 - k);
        let (nu, nv) = (sp.states(0), sp.states(1));
        let stride = SLOTS * n;
        let (s, d, gamma) = (self.weights.alpha, self.weights.d, self.weights.gamma);
        let scale = self.data.scale;
        let wk = sp.window[k] as i32;
        let offsets = &sp.offset[k];
        let mut outbox = vec![0f32; w * n];
        // Scratch, allocated once per strip: belief sum, the three outgoing
        // costs (along the row, across rows, to the other layer), one message.
        let mut scratch = vec![0f32; 5 * n];
        let (sum, rest) = scratch.split_at_mut(n);
        let (horiz, rest) = rest.split_at_mut(n);
        let (vert, rest) = rest.split_at_mut(n);
        let (dual_h, msg) = rest.split_at_mut(n);
        let (skip_h, skip_v) = if self.forward {
            (FROM_RIGHT, FROM_DOWN)
        } else {
            (FROM_LEFT, FROM_UP)
        };

        for r in 0..y1 - y0 {
            let y = if self.forward { y0 + r } else { y1 - 1 - r };
            for i in 0..w {
                let x = if self.forward { i } else { w - 1 - i };
                let p = y * w + x;
                let pl = (y - y0) * w + x;
                let node = &mk[pl * stride..(pl + 1) * stride];
                let base = offsets[p] - wk;
                for (l, a) in sum.iter_mut().enumerate() {
                    *a = gamma * (base + l as i32).unsigned_abs() as f32;
                }
                for m in node.chunks_exact(n) {
                    for (a, &v) in sum.iter_mut().zip(m) {
                        *a += v;
                    }
                }
                let slot = |j: usize| &node[j * n..(j + 1) * n];
                for (((hz, vt), (du, &a)), ((&mh, &mv), &md)) in horiz
                    .iter_mut()
                    .zip(vert.iter_mut())
                    .zip(dual_h.iter_mut().zip(sum.iter()))
                    .zip(slot(skip_h).iter().zip(slot(skip_v)).zip(slot(FROM_DUAL)))
                {
                    *hz = a - mh;
                    *vt = a - mv;
                    *du = a - md;
                }

                // Along the row.
                let along = if self.forward {
                    (x + 1 < w).then(|| p + 1)
                } else {
                    (x > 0).then(|| p - 1)
                };
                if let Some(q) = along {
                    let shift = offsets[q] - offsets[p];
                    spatial_message(horiz, shift, s, d, msg);
                    let (ql, into) = if self.forward {
                        (pl + 1, FROM_LEFT)
                    } else {
                        (pl - 1, FROM_RIGHT)
                    };
                    let dst = ql * stride + into * n;
                    mk[dst..dst + n].copy_from_slice(msg);
                }
                // Across rows.
                let across = if self.forward {
                    (y + 1 < h).then(|| p + w)
                } else {
                    (y > 0).then(|| p - w)
                };
                if let Some(q) = across {
                    let shift = offsets[q] - offsets[p];
                    spatial_message(vert, shift, s, d, msg);
                    let inside = if self.forward { y + 1 < y1 } else { y > y0 };
                    if inside {
                        let (ql, into) = if self.forward {
                            (pl + w, FROM_UP)
                        } else {
                            (pl - w, FROM_DOWN)
                        };
                        let dst = ql * stride + into * n;
                        mk[dst..dst + n].copy_from_slice(msg);
                    } else {
                        outbox[x * n..(x + 1) * n].copy_from_slice(msg);
                    }
                }
                if self.dual {
                    let cost = self.data.pixel(p, nu * nv);
                    let dst = (pl * SLOTS + FROM_DUAL) * no;
                    dual_message(k, dual_h, cost, scale, nu, &mut mo[dst..dst + no]);
                }
            }
        }
        outbox
    }
}

impl<'a> DualLayerBp<'a> {
    /// A solver with all messages at zero. `min_strip_rows`/`max_strips`
    /// control the strip parallelism (`max_strips = 1`: strictly sequential).
    ///
    /// # Panics
    /// When a layer has more than [`MAX_STATES`] states (checked by the caller's
    /// parameter validation).
    #[must_use]
    pub fn new(
        space: &'a LabelSpace,
        data: &'a DataTerm,
        weights: EnergyWeights,
        min_strip_rows: usize,
        max_strips: usize,
    ) -> Self {
        assert!(space.states(0) <= MAX_STATES && space.states(1) <= MAX_STATES);
        let area = space.width * space.height;
        let msgs = [
            vec![0f32; area * SLOTS * space.states(0)],
            vec![0f32; area * SLOTS * space.states(1)],
        ];
        Self {
            space,
            data,
            weights,
            msgs,
            strips: strips_for(space.height, min_strip_rows, max_strips),
            min_strip_rows,
            max_strips,
        }
    }

    /// Multigrid initialisation (the reference code's "hierarchy"): solves
    /// the problem on `hierarchy` successively coarser grids of 2 × 2 nodes,
    /// where the data term is 4× stronger against the smoothness, `iterations`
    /// each, and starts this grid's messages from the coarse ones. Without it,
    /// a strong smoothness lets the first sweeps lock the flow at its initial
    /// offsets.
    pub fn warm_start(&mut self, hierarchy: usize, iterations: usize) {
        if hierarchy == 0 || self.space.width < 2 || self.space.height < 2 {
            return;
        }
        let (cspace, cdata) = self.data.coarsen(self.space);
        let cweights = EnergyWeights {
            gamma: self.weights.gamma / 2.0,
            ..self.weights
        };
        let mut coarse = DualLayerBp::new(
            &cspace,
            &cdata,
            cweights,
            self.min_strip_rows,
            self.max_strips,
        );
        coarse.warm_start(hierarchy - 1, iterations);
        for count in 0..iterations {
            coarse.iterate(count);
        }
        // Every node takes the messages of its coarse parent, label-aligned.
        let w = self.space.width;
        for k in 0..2 {
            let n = self.space.states(k);
            let src = &coarse.msgs[k];
            let cw = cspace.width;
            let offsets = &self.space.offset[k];
            let coffsets = &cspace.offset[k];
            self.msgs[k]
                .par_chunks_mut(w * SLOTS * n)
                .enumerate()
                .for_each(|(y, row)| {
                    for (x, node) in row.chunks_exact_mut(SLOTS * n).enumerate() {
                        let c = (y / 2) * cw + x / 2;
                        let shift = offsets[y * w + x] - coffsets[c];
                        let cnode = &src[c * SLOTS * n..(c + 1) * SLOTS * n];
                        for slot in 0..SLOTS {
                            for l in 0..n {
                                node[slot * n + l] = cnode[slot * n + clamp_label(l, shift, n)];
                            }
                        }
                    }
                });
        }
    }

    /// One iteration `count` of the BP-S schedule.
    fn iterate(&mut self, count: usize) {
        let k = count % 2;
        let forward = count % 4 < 2;
        let dual = count % 8 < 4;
        let w = self.space.width;
        let n = [self.space.states(0), self.space.states(1)];
        let sweep = Sweep {
            space: self.space,
            data: self.data,
            weights: self.weights,
            k,
            forward,
            dual,
        };
        let [m0, m1] = &mut self.msgs;
        let (mk, mo) = if k == 0 { (m0, m1) } else { (m1, m0) };
        let strips = self.strips.clone();
        let outboxes: Vec<Vec<f32>> = {
            let sk = split_strips(mk, &strips, w * SLOTS * n[k]);
            let so = split_strips(mo, &strips, w * SLOTS * n[1 - k]);
            sk.into_par_iter()
                .zip(so)
                .zip(strips.par_iter())
                .map(|((a, b), &(y0, y1))| sweep.strip(y0, y1, a, b))
                .collect()
        };
        // Deliver the messages that crossed a strip boundary.
        let nk = n[k];
        for (i, outbox) in outboxes.iter().enumerate() {
            let (y0, y1) = strips[i];
            let (row, slot) = if forward {
                if i + 1 == strips.len() {
                    continue;
                }
                (y1, FROM_UP)
            } else {
                if i == 0 {
                    continue;
                }
                (y0 - 1, FROM_DOWN)
            };
            for x in 0..w {
                let dst = ((row * w + x) * SLOTS + slot) * nk;
                mk[dst..dst + nk].copy_from_slice(&outbox[x * nk..(x + 1) * nk]);
            }
        }
    }

    /// Beliefs of layer `k` at pixel `p`: range term plus every incoming message.
    pub fn belief(&self, k: usize, p: usize, out: &mut [f32]) {
        let n = self.space.states(k);
        let node = &self.msgs[k][p * SLOTS * n..(p + 1) * SLOTS * n];
        for (l, o) in out[..n].iter_mut().enumerate() {
            let mut b = self.weights.gamma * self.space.flow(k, p, l).unsigned_abs() as f32;
            for slot in 0..SLOTS {
                b += node[slot * n + l];
            }
            *o = b;
        }
    }

    /// The argmin of the beliefs of every pixel, per layer.
    #[must_use]
    pub fn labels(&self) -> [Vec<u16>; 2] {
        let area = self.space.width * self.space.height;
        let layer = |k: usize| -> Vec<u16> {
            (0..area)
                .into_par_iter()
                .map_init(
                    || [0f32; MAX_STATES],
                    |buf, p| {
                        self.belief(k, p, buf);
                        let n = self.space.states(k);
                        let mut best = 0;
                        for l in 1..n {
                            if buf[l] < buf[best] {
                                best = l;
                            }
                        }
                        // best < MAX_STATES < 2^16.
                        #[allow(clippy::cast_possible_truncation)]
                        let b = best as u16;
                        b
                    },
                )
                .collect()
        };
        [layer(0), layer(1)]
    }

    /// Per pixel of layer `k`: the belief of the best label that is not
    /// `labels[p]` or next to it, minus the belief of `labels[p]` (0 when the
    /// window has no such label). Large means unambiguous.
    #[must_use]
    pub fn margins(&self, k: usize, labels: &[u16]) -> Vec<f32> {
        let n = self.space.states(k);
        (0..labels.len())
            .into_par_iter()
            .map_init(
                || [0f32; MAX_STATES],
                |buf, p| {
                    self.belief(k, p, buf);
                    let best = usize::from(labels[p]);
                    let second = (0..n)
                        .filter(|&l| l + 1 < best || l > best + 1)
                        .map(|l| buf[l])
                        .fold(f32::INFINITY, f32::min);
                    if second.is_finite() {
                        (second - buf[best]).max(0.0)
                    } else {
                        0.0
                    }
                },
            )
            .collect()
    }

    /// Runs `iterations` iterations, recording the energy after each.
    pub fn run(&mut self, iterations: usize) -> BpOutcome {
        let mut energies = Vec::with_capacity(iterations);
        let mut labels = self.labels();
        for count in 0..iterations {
            self.iterate(count);
            labels = self.labels();
            energies.push(energy(self.data, self.space, &labels, &self.weights));
        }
        BpOutcome {
            labels,
            energy: energies,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The min-sum message by its definition, O(n²):
    /// `m(l1) = min_lp h(lp) + min(s |lp − (l1 + shift)|, d)`, normalised.
    fn naive_message(h: &[f32], shift: i32, s: f32, d: f32) -> Vec<f32> {
        let n = h.len() as i32;
        let m: Vec<f32> = (0..n)
            .map(|l1| {
                (0..n)
                    .map(|lp| h[lp as usize] + (s * (lp - (l1 + shift)).abs() as f32).min(d))
                    .fold(f32::INFINITY, f32::min)
            })
            .collect();
        let min = m.iter().copied().fold(f32::INFINITY, f32::min);
        m.iter().map(|v| v - min).collect()
    }

    #[test]
    fn distance_transform_message_matches_definition() {
        let mut seed = 7u32;
        let mut rnd = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        for n in [1usize, 3, 5, 21] {
            for shift in [-25, -3, -1, 0, 2, 7, 30] {
                for &(s, d) in &[(1.0f32, 4.0f32), (2.0, 40.0), (0.5, 0.7)] {
                    let h: Vec<f32> = (0..n).map(|_| 10.0 * rnd()).collect();
                    let want = naive_message(&h, shift, s, d);
                    let mut hh = h.clone();
                    let mut got = vec![0f32; n];
                    spatial_message(&mut hh, shift, s, d, &mut got);
                    for (a, b) in got.iter().zip(&want) {
                        assert!(
                            (a - b).abs() < 1e-4,
                            "n {n} shift {shift}: {got:?} vs {want:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn dual_message_matches_definition() {
        let (nu, nv) = (5, 3);
        let cost: Vec<u16> = (0..nu * nv).map(|i| ((i * 37) % 23) as u16).collect();
        let hu: Vec<f32> = (0..nu).map(|i| (i as f32 - 2.0).abs() * 1.5).collect();
        let hv: Vec<f32> = vec![3.0, 0.0, 1.0];
        let mut got = vec![0f32; nv];
        dual_message(0, &hu, &cost, 1.0, nu, &mut got);
        let want: Vec<f32> = (0..nv)
            .map(|lv| {
                (0..nu)
                    .map(|lu| hu[lu] + f32::from(cost[lv * nu + lu]))
                    .fold(f32::INFINITY, f32::min)
            })
            .collect();
        let m = want.iter().copied().fold(f32::INFINITY, f32::min);
        assert_eq!(got, want.iter().map(|v| v - m).collect::<Vec<_>>());

        let mut got = vec![0f32; nu];
        dual_message(1, &hv, &cost, 1.0, nu, &mut got);
        let want: Vec<f32> = (0..nu)
            .map(|lu| {
                (0..nv)
                    .map(|lv| hv[lv] + f32::from(cost[lv * nu + lu]))
                    .fold(f32::INFINITY, f32::min)
            })
            .collect();
        let m = want.iter().copied().fold(f32::INFINITY, f32::min);
        assert_eq!(got, want.iter().map(|v| v - m).collect::<Vec<_>>());
    }

    /// A small synthetic problem: the data term prefers `u = 2` on the left
    /// half and `u = −1` on the right, with noise; v prefers 0.
    fn problem(w: usize, h: usize) -> (LabelSpace, DataTerm) {
        let space = LabelSpace {
            width: w,
            height: h,
            window: [3, 1],
            offset: [vec![0; w * h], vec![0; w * h]],
        };
        let (nu, nv) = (7, 3);
        let mut cost = vec![0u16; w * h * nu * nv];
        let mut seed = 1u32;
        for p in 0..w * h {
            let truth = if p % w < w / 2 { 2 } else { -1 };
            for lv in 0..nv {
                for lu in 0..nu {
                    seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    let noise = (seed >> 20) % 60;
                    let du = (lu as i32 - 3 - truth).unsigned_abs();
                    let dv = (lv as i32 - 1).unsigned_abs();
                    cost[(p * nv + lv) * nu + lu] = (40 * du + 40 * dv + noise) as u16;
                }
            }
        }
        (
            space,
            DataTerm {
                cost,
                scale: 1.0,
                outside_cost: 0,
            },
        )
    }

    #[test]
    fn bp_lowers_the_energy_and_recovers_the_labels() {
        let (space, data) = problem(24, 70);
        let weights = EnergyWeights {
            alpha: 20.0,
            d: 200.0,
            gamma: 1.0,
        };
        let zero = [vec![3u16; 24 * 70], vec![1u16; 24 * 70]];
        let e0 = energy(&data, &space, &zero, &weights);
        for max_strips in [1, 3] {
            let mut bp = DualLayerBp::new(&space, &data, weights, 16, max_strips);
            let out = bp.run(16);
            assert!(*out.energy.last().unwrap() < 0.5 * e0);
            let wrong = (0..24 * 70)
                .filter(|&p| {
                    let truth = if p % 24 < 12 { 2 } else { -1 };
                    space.flow(0, p, usize::from(out.labels[0][p])) != truth
                        || space.flow(1, p, usize::from(out.labels[1][p])) != 0
                })
                .count();
            assert!(
                wrong <= 24 * 70 / 100,
                "{max_strips} strips: {wrong} wrong labels"
            );
        }
    }
}
