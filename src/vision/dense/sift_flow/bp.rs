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

use crate::vision::pages;

use super::energy::{
    DataTerm, EdgeTruncation, EnergyWeights, LabelSpace, clamp_label, energy_with,
};

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
    /// Per-edge truncation instead of `weights.d` (see [`DualLayerBp::truncate_edges`]).
    edges: Option<&'a EdgeTruncation>,
    /// Per layer: `msgs[k][(p · SLOTS + slot) · n_k + l]`; empty until a step sets them
    /// ([`DualLayerBp::set_messages`]): the warm start writes every one, no zeros first.
    msgs: [Vec<f32>; 2],
    /// The messages of the warm-start grids, kept between runs ([`BpBuffers`]).
    coarse: Option<Box<BpBuffers>>,
    /// Per layer: the argmin of every pixel's belief, kept current by the sweeps.
    labels: [Vec<u16>; 2],
    /// Whether `labels` are those of the current messages: the
    /// initialisations change messages without recomputing them, and a run
    /// recomputes them once before it starts (for the test of settled labels).
    labels_current: bool,
    strips: Vec<(usize, usize)>,
    /// Per row, the columns the sweeps visit (all by default, see
    /// [`DualLayerBp::restrict`]).
    spans: Vec<(usize, usize)>,
    min_strip_rows: usize,
    max_strips: usize,
}

/// The message memory of a [`DualLayerBp`] and of its warm-start grids behind it. A matcher
/// hands it from level to level and direction to direction, reserved once for its largest
/// grids ([`BpBuffers::reserve`]): the memory is touched once, not again for every solve.
#[derive(Debug, Default)]
pub struct BpBuffers {
    msgs: [Vec<f32>; 2],
    coarse: Option<Box<BpBuffers>>,
}

impl BpBuffers {
    /// Buffers with room for the messages of a `width × height` grid with `states` per layer
    /// and of its `hierarchy` warm-start grids, without touching the memory.
    #[must_use]
    pub fn reserve(width: usize, height: usize, states: [usize; 2], hierarchy: usize) -> Self {
        let mut out = Self::default();
        out.grow(width, height, states, hierarchy);
        out
    }

    /// Grows the room to that of [`BpBuffers::reserve`] for the given grid (kept if larger).
    pub fn grow(&mut self, width: usize, height: usize, states: [usize; 2], hierarchy: usize) {
        for (m, n) in self.msgs.iter_mut().zip(states) {
            let len = width * height * SLOTS * n;
            if m.capacity() < len {
                // The old contents are never read: no copy.
                *m = room(len);
            }
        }
        if hierarchy > 0 && width >= 2 && height >= 2 {
            self.coarse.get_or_insert_default().grow(
                width.div_ceil(2),
                height.div_ceil(2),
                states,
                hierarchy - 1,
            );
        }
    }

    /// Bytes of message memory reserved, all grids.
    #[must_use]
    pub fn capacity_bytes(&self) -> usize {
        self.msgs.iter().map(Vec::capacity).sum::<usize>() * size_of::<f32>()
            + self.coarse.as_ref().map_or(0, |c| c.capacity_bytes())
    }
}

/// An empty buffer with room for `len` messages, on huge pages when it is large: the first
/// sweep touches all of it ([`crate::vision::pages`]).
fn room(len: usize) -> Vec<f32> {
    pages::room(len)
}

/// `v` holding `len` zeros, in its own memory when it has room (cleared in parallel: a
/// message buffer is tens of MB).
fn zeroed(mut v: Vec<f32>, len: usize) -> Vec<f32> {
    if v.capacity() < len {
        // Fresh zeroed memory costs no writes.
        return pages::zeroed(len);
    }
    v.clear();
    v.spare_capacity_mut()[..len]
        .par_chunks_mut(ZERO_CHUNK)
        .for_each(|c| c.fill(std::mem::MaybeUninit::new(0.0)));
    // SAFETY: the first `len` elements (within the capacity checked above) were all written.
    unsafe {
        v.set_len(len);
    }
    v
}

/// Elements cleared by one task of [`zeroed`].
const ZERO_CHUNK: usize = 1 << 16;

/// What [`DualLayerBp::run`] returns.
#[derive(Debug, Clone)]
pub struct BpOutcome {
    /// The label of every pixel per layer (argmin of the beliefs).
    pub labels: [Vec<u16>; 2],
    /// Energy (10) after each iteration (the paper's Fig. 8).
    pub energy: Vec<f64>,
}

/// Splits `v` into consecutive mutable row blocks, one per strip.
fn split_strips<'b, T>(
    mut v: &'b mut [T],
    strips: &[(usize, usize)],
    row_len: usize,
) -> Vec<&'b mut [T]> {
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

/// Per row, the columns `x0..x1` of the nodes within `margin` pixels
/// (Chebyshev distance) of an active one; `(0, 0)` for a row with none.
/// Rows of an image rotated onto the rectified canvas hold one interval of
/// real pixels each, so the bounding interval loses little.
#[must_use]
pub fn active_spans(active: &[bool], w: usize, h: usize, margin: usize) -> Vec<(usize, usize)> {
    assert_eq!(active.len(), w * h, "mask size");
    let own: Vec<(usize, usize)> = active
        .chunks_exact(w)
        .map(
            |row| match (row.iter().position(|&a| a), row.iter().rposition(|&a| a)) {
                (Some(first), Some(last)) => (first, last + 1),
                _ => (0, 0),
            },
        )
        .collect();
    (0..h)
        .map(|y| {
            bounding(&own[y.saturating_sub(margin)..(y + margin + 1).min(h)])
                .map_or((0, 0), |(a, b)| {
                    (a.saturating_sub(margin), (b + margin).min(w))
                })
        })
        .collect()
}

/// The interval that holds every non-empty one of `spans` (`None`: all empty).
fn bounding(spans: &[(usize, usize)]) -> Option<(usize, usize)> {
    let mut filled = spans.iter().filter(|s| s.1 > s.0);
    let first = *filled.next()?;
    Some(filled.fold(first, |(a, b), s| (a.min(s.0), b.max(s.1))))
}

/// The spans of [`active_spans`] on the grid of 2 × 2 nodes (width `cw`).
fn coarsen_spans(spans: &[(usize, usize)], cw: usize, ch: usize) -> Vec<(usize, usize)> {
    (0..ch)
        .map(|cy| {
            bounding(&spans[2 * cy..(2 * cy + 2).min(spans.len())])
                .map_or((0, 0), |(a, b)| (a / 2, b.div_ceil(2).min(cw)))
        })
        .collect()
}

/// `min` that compiles to one instruction (no NaN handling: messages are finite).
#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if b < a { b } else { a }
}

/// Index of the smallest entry (the first one on ties).
///
/// The best value is carried beside its index and both are selected, not branched on: the
/// winner of a few beliefs is data-dependent, so a branch mispredicts about every other node.
#[inline(always)]
fn argmin(v: &[f32]) -> u16 {
    let mut best = 0;
    let mut best_value = v[0];
    for (l, &x) in v.iter().enumerate().skip(1) {
        let better = x < best_value;
        best = if better { l } else { best };
        best_value = if better { x } else { best_value };
    }
    // Fewer than MAX_STATES < 2^16 states.
    #[allow(clippy::cast_possible_truncation)]
    let b = best as u16;
    b
}

/// The message from a node with cost `h` (over its `n` labels) to a
/// neighbour whose offset is `shift` labels further: distance transform with
/// slope `s`, truncation at `min h + d`, normalised to a zero minimum.
#[inline(always)]
fn spatial_message(h: &mut [f32], shift: i32, s: f32, d: f32, out: &mut [f32]) {
    let n = h.len();
    let mut cap = h[0];
    for l in 1..n {
        cap = fmin(cap, h[l]);
        h[l] = fmin(h[l], h[l - 1] + s);
    }
    let cap = cap + d;
    for l in (0..n - 1).rev() {
        h[l] = fmin(h[l], h[l + 1] + s);
    }
    let mut min = f32::INFINITY;
    if shift == 0 {
        for (o, &v) in out.iter_mut().zip(h.iter()) {
            let v = fmin(v, cap);
            min = fmin(min, v);
            *o = v;
        }
    } else {
        let n_i = n as i32;
        for (l1, o) in out.iter_mut().enumerate() {
            let lp = l1 as i32 + shift;
            let v = if lp < 0 {
                h[0] + s * (-lp) as f32
            } else if lp >= n_i {
                h[n - 1] + s * (lp - n_i + 1) as f32
            } else {
                h[lp as usize]
            };
            let v = fmin(v, cap);
            min = fmin(min, v);
            *o = v;
        }
    }
    for o in out.iter_mut() {
        *o -= min;
    }
}

/// The message from layer `k` to the other layer of the same pixel:
/// `m(l') = min_l h(l) + scale · D(l, l')`, normalised. `cost` is `[l_v][l_u]`.
#[inline(always)]
fn dual_message(k: usize, h: &[f32], cost: &[u16], scale: f32, nu: usize, out: &mut [f32]) {
    if k == 0 {
        // u → v: for every l_v, min over l_u (contiguous).
        for (o, row) in out.iter_mut().zip(cost.chunks_exact(nu)) {
            let mut m = f32::INFINITY;
            for (&c, &a) in row.iter().zip(h) {
                m = fmin(m, a + scale * f32::from(c));
            }
            *o = m;
        }
    } else {
        // v → u: running minimum over l_v, vectorised along l_u.
        out.fill(f32::INFINITY);
        for (&a, row) in h.iter().zip(cost.chunks_exact(nu)) {
            for (o, &c) in out.iter_mut().zip(row) {
                *o = fmin(*o, a + scale * f32::from(c));
            }
        }
    }
    let mut min = out[0];
    for &o in out.iter() {
        min = fmin(min, o);
    }
    for o in out.iter_mut() {
        *o -= min;
    }
}

/// One sweep's read-only context.
struct Sweep<'c> {
    space: &'c LabelSpace,
    data: &'c DataTerm,
    weights: EnergyWeights,
    edges: Option<&'c EdgeTruncation>,
    k: usize,
    forward: bool,
    dual: bool,
    /// Per row, the columns that are swept.
    spans: &'c [(usize, usize)],
}

/// The mutable rows of one strip.
struct StripRows<'m> {
    y0: usize,
    y1: usize,
    /// Layer `k`'s messages and labels, layer `1 − k`'s messages and labels.
    mk: &'m mut [f32],
    mo: &'m mut [f32],
    lk: &'m mut [u16],
    lo: &'m mut [u16],
}

impl Sweep<'_> {
    /// Sweeps the rows of one strip of layer `k`, keeping the labels of both
    /// layers current. Returns the messages that leave the strip (downwards
    /// from its last row or upwards from its first), one per column.
    ///
    /// `N`/`NO` are the state counts of layer `k` and of the other layer when
    /// known at compile time (0: read them from the label space); the common
    /// sizes are monomorphised so the short loops unroll.
    #[inline(always)]
    fn strip<const N: usize, const NO: usize>(&self, rows: StripRows<'_>) -> Vec<f32> {
        let StripRows {
            y0,
            y1,
            mk,
            mo,
            lk,
            lo,
        } = rows;
        let sp = self.space;
        let (w, h) = (sp.width, sp.height);
        let k = self.k;
        let n = if N > 0 { N } else { sp.states(k) };
        let no = if NO > 0 { NO } else { sp.states(1 - k) };
        let nu = if k == 0 { n } else { no };
        let per = n * no;
        let stride = SLOTS * n;
        let stride_o = SLOTS * no;
        let (s, d, gamma) = (self.weights.alpha, self.weights.d, self.weights.gamma);
        let scale = self.data.scale;
        let wk = sp.window[k] as i32;
        let wo = sp.window[1 - k] as i32;
        let offsets = &sp.offset[k];
        let offsets_o = &sp.offset[1 - k];
        let mut outbox = vec![0f32; w * n];
        let mut scratch = [0f32; 5 * MAX_STATES];
        let (sum, rest) = scratch.split_at_mut(n);
        let (horiz, rest) = rest.split_at_mut(n);
        let (vert, rest) = rest.split_at_mut(n);
        let (dual_h, rest) = rest.split_at_mut(n);
        let msg = &mut rest[..n];
        let mut belief_o = [0f32; MAX_STATES];
        let belief_o = &mut belief_o[..no];
        let (skip_h, skip_v) = if self.forward {
            (FROM_RIGHT, FROM_DOWN)
        } else {
            (FROM_LEFT, FROM_UP)
        };

        for r in 0..y1 - y0 {
            let y = if self.forward { y0 + r } else { y1 - 1 - r };
            let (xa, xb) = self.spans[y];
            for i in 0..xb.saturating_sub(xa) {
                let x = if self.forward { xa + i } else { xb - 1 - i };
                let p = y * w + x;
                let pl = (y - y0) * w + x;
                let node = &mk[pl * stride..pl * stride + stride];
                let base = offsets[p] - wk;
                for (l, a) in sum.iter_mut().enumerate() {
                    *a = gamma * (base + l as i32).unsigned_abs() as f32;
                }
                for m in node.chunks_exact(n) {
                    for (a, &v) in sum.iter_mut().zip(m) {
                        *a += v;
                    }
                }
                // Every message into this node is final for this sweep: its
                // belief's argmin is the layer's new label.
                lk[pl] = argmin(sum);
                let mh = &node[skip_h * n..skip_h * n + n];
                let mv = &node[skip_v * n..skip_v * n + n];
                let md = &node[FROM_DUAL * n..FROM_DUAL * n + n];
                for l in 0..n {
                    horiz[l] = sum[l] - mh[l];
                    vert[l] = sum[l] - mv[l];
                    dual_h[l] = sum[l] - md[l];
                }

                // Along the row.
                let along = if self.forward {
                    (x + 1 < w).then(|| p + 1)
                } else {
                    (x > 0).then(|| p - 1)
                };
                if let Some(q) = along {
                    let d = self.edges.map_or(d, |e| e.right[p.min(q)]);
                    spatial_message(horiz, offsets[q] - offsets[p], s, d, msg);
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
                    let d = self.edges.map_or(d, |e| e.down[p.min(q)]);
                    spatial_message(vert, offsets[q] - offsets[p], s, d, msg);
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
                        outbox[x * n..x * n + n].copy_from_slice(msg);
                    }
                }
                if self.dual {
                    let cost = &self.data.cost[p * per..p * per + per];
                    let onode = &mut mo[pl * stride_o..pl * stride_o + stride_o];
                    dual_message(
                        k,
                        dual_h,
                        cost,
                        scale,
                        nu,
                        &mut onode[FROM_DUAL * no..FROM_DUAL * no + no],
                    );
                    // The other layer's belief changed only through this message.
                    let base_o = offsets_o[p] - wo;
                    for (l, b) in belief_o.iter_mut().enumerate() {
                        *b = gamma * (base_o + l as i32).unsigned_abs() as f32;
                    }
                    for m in onode.chunks_exact(no) {
                        for (b, &v) in belief_o.iter_mut().zip(m) {
                            *b += v;
                        }
                    }
                    lo[pl] = argmin(belief_o);
                }
            }
        }
        outbox
    }

    /// [`Self::strip`] for the state counts at hand.
    fn strip_dispatch(&self, rows: StripRows<'_>) -> Vec<f32> {
        let n = self.space.states(self.k);
        let no = self.space.states(1 - self.k);
        match (n, no) {
            (3, 3) => self.strip::<3, 3>(rows),
            (5, 3) => self.strip::<5, 3>(rows),
            (3, 5) => self.strip::<3, 5>(rows),
            (5, 5) => self.strip::<5, 5>(rows),
            // The improved preset's middle level (half windows 4 and 1).
            (9, 3) => self.strip::<9, 3>(rows),
            (3, 9) => self.strip::<3, 9>(rows),
            (21, 5) => self.strip::<21, 5>(rows),
            (5, 21) => self.strip::<5, 21>(rows),
            (21, 21) => self.strip::<21, 21>(rows),
            _ => self.strip::<0, 0>(rows),
        }
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
        Self::with_buffers(
            space,
            data,
            weights,
            min_strip_rows,
            max_strips,
            BpBuffers::default(),
        )
    }

    /// [`DualLayerBp::new`] keeping its messages in `buffers` (grown when too small); get
    /// them back with [`DualLayerBp::into_buffers`].
    ///
    /// # Panics
    /// As [`DualLayerBp::new`].
    #[must_use]
    pub fn with_buffers(
        space: &'a LabelSpace,
        data: &'a DataTerm,
        weights: EnergyWeights,
        min_strip_rows: usize,
        max_strips: usize,
        buffers: BpBuffers,
    ) -> Self {
        assert!(space.states(0) <= MAX_STATES && space.states(1) <= MAX_STATES);
        let area = space.width * space.height;
        let BpBuffers {
            msgs: [m0, m1],
            coarse,
        } = buffers;
        // Emptied, not zeroed: the room is kept for whichever step sets the messages first.
        let msgs = [m0, m1].map(|mut m| {
            m.clear();
            m
        });
        Self {
            space,
            data,
            weights,
            edges: None,
            msgs,
            coarse,
            labels: [vec![0; area], vec![0; area]],
            labels_current: false,
            strips: strips_for(space.height, min_strip_rows, max_strips),
            spans: vec![(0, space.width); space.height],
            min_strip_rows,
            max_strips,
        }
    }

    /// The message memory, for the next solver.
    #[must_use]
    pub fn into_buffers(self) -> BpBuffers {
        BpBuffers {
            msgs: self.msgs,
            coarse: self.coarse,
        }
    }

    /// Frees the messages of the warm-start grids (kept for the next solver otherwise): for the
    /// last, largest grid, whose iterations would hold them for nothing.
    pub fn release_warm_start_buffers(&mut self) {
        self.coarse = None;
    }

    /// Sweeps only the columns `spans[y]` of every row `y` (for instance the
    /// [`active_spans`] of the pixels that carry a data term): the nodes
    /// outside are left out of the graph — they send no message, and their
    /// labels are not a solution — and the nodes inside read the messages
    /// they last received from them (none, or the warm start's). On a canvas
    /// that an oblique tilt axis rotates, about half the nodes lie outside.
    ///
    /// # Panics
    /// When `spans` does not have one interval within the width per row.
    pub fn restrict(&mut self, spans: Vec<(usize, usize)>) {
        assert_eq!(spans.len(), self.space.height, "one span per row");
        assert!(
            spans.iter().all(|&(a, b)| a <= b && b <= self.space.width),
            "spans within the width"
        );
        self.spans = spans;
    }

    /// Truncates the smoothness of every edge at its own value in `edges`
    /// instead of `d` (a contrast-sensitive truncation). The coarser grids
    /// of [`DualLayerBp::warm_start`] keep `d`: they only start the messages.
    pub fn truncate_edges(&mut self, edges: &'a EdgeTruncation) {
        let n = self.space.width * self.space.height;
        assert!(
            edges.right.len() == n && edges.down.len() == n,
            "one truncation per pixel and direction"
        );
        self.edges = Some(edges);
    }

    /// All messages at zero unless a step has set them already (the warm start writes every
    /// one: zeroing its room first would be a pass over the largest buffer for nothing).
    fn set_messages(&mut self) {
        let area = self.space.width * self.space.height;
        for (k, m) in self.msgs.iter_mut().enumerate() {
            let len = area * SLOTS * self.space.states(k);
            if m.len() != len {
                *m = zeroed(std::mem::take(m), len);
            }
        }
    }

    /// Recomputes the labels if the messages changed since they were taken.
    fn refresh_labels(&mut self) {
        self.set_messages();
        if !self.labels_current {
            self.labels = self.all_labels();
            self.labels_current = true;
        }
    }

    /// Multigrid initialisation (the reference code's "hierarchy"): solves
    /// the problem on `hierarchy` successively coarser grids of 2 × 2 nodes,
    /// where the data term is 4× stronger against the smoothness, `iterations`
    /// each, and starts this grid's messages from the coarse ones. Without it,
    /// a strong smoothness lets the first sweeps lock the flow at its initial
    /// offsets.
    pub fn warm_start(&mut self, hierarchy: usize, iterations: usize) {
        if !self.warm_start_replaces_messages(hierarchy) {
            return;
        }
        let (cspace, cdata) = self.data.coarsen(self.space);
        let cweights = EnergyWeights {
            gamma: self.weights.gamma / 2.0,
            ..self.weights
        };
        let mut coarse = DualLayerBp::with_buffers(
            &cspace,
            &cdata,
            cweights,
            self.min_strip_rows,
            self.max_strips,
            self.coarse.take().map(|b| *b).unwrap_or_default(),
        );
        coarse.restrict(coarsen_spans(&self.spans, cspace.width, cspace.height));
        coarse.warm_start(hierarchy - 1, iterations);
        for count in 0..iterations {
            coarse.iterate(count);
        }
        // Every node takes the messages of its coarse parent, label-aligned, written into the
        // room of the messages without zeroing it first.
        let w = self.space.width;
        let area = w * self.space.height;
        for k in 0..2 {
            let n = self.space.states(k);
            let len = area * SLOTS * n;
            let src = &coarse.msgs[k];
            let cw = cspace.width;
            let offsets = &self.space.offset[k];
            let coffsets = &cspace.offset[k];
            let msgs = &mut self.msgs[k];
            msgs.clear();
            if msgs.capacity() < len {
                *msgs = room(len);
            }
            msgs.spare_capacity_mut()[..len]
                .par_chunks_mut(w * SLOTS * n)
                .enumerate()
                .for_each(|(y, row)| {
                    let mut from = [0usize; MAX_STATES];
                    for (x, node) in row.chunks_exact_mut(SLOTS * n).enumerate() {
                        let c = (y / 2) * cw + x / 2;
                        let shift = offsets[y * w + x] - coffsets[c];
                        let cnode = &src[c * SLOTS * n..(c + 1) * SLOTS * n];
                        // Mostly the parent's own offset: a plain copy.
                        if shift == 0 {
                            for (o, &v) in node.iter_mut().zip(cnode) {
                                o.write(v);
                            }
                            continue;
                        }
                        for (l, f) in from[..n].iter_mut().enumerate() {
                            *f = clamp_label(l, shift, n);
                        }
                        for (slot, cslot) in node.chunks_exact_mut(n).zip(cnode.chunks_exact(n)) {
                            for (o, &f) in slot.iter_mut().zip(&from[..n]) {
                                o.write(cslot[f]);
                            }
                        }
                    }
                });
            // SAFETY: the rows above are the `height` rows of `width` nodes of `SLOTS · n`
            // messages each, `len` in all, and every message of every node was written (a
            // copy of its parent's node, or each slot label by label): the first `len`
            // elements are initialised `f32`s, within the capacity checked above.
            unsafe {
                msgs.set_len(len);
            }
        }
        self.coarse = Some(Box::new(coarse.into_buffers()));
        self.labels_current = false;
    }

    /// Whether [`DualLayerBp::warm_start`] with `hierarchy` grids sets every message (it leaves
    /// them alone on a grid too small to coarsen).
    #[must_use]
    pub fn warm_start_replaces_messages(&self, hierarchy: usize) -> bool {
        hierarchy > 0 && self.space.width >= 2 && self.space.height >= 2
    }

    /// Starts both layers' inter-layer messages from the data term (the
    /// message each node would send with only its range term): without it the
    /// first sweep sees no data and spreads the small-displacement prior over
    /// the whole grid, which the strong smoothness then keeps.
    pub fn init_dual_from_data(&mut self) {
        self.set_messages();
        let sp = self.space;
        let (nu, nv) = (sp.states(0), sp.states(1));
        let gamma = self.weights.gamma;
        let scale = self.data.scale;
        let data = self.data;
        for k in 0..2 {
            let (n, no) = (sp.states(k), sp.states(1 - k));
            let (target, _) = if k == 0 {
                let [a, b] = &mut self.msgs;
                (b, a)
            } else {
                let [a, b] = &mut self.msgs;
                (a, b)
            };
            target.par_chunks_mut(SLOTS * no).enumerate().for_each_init(
                || vec![0f32; n],
                |h, (p, node)| {
                    let base = sp.offset[k][p] - sp.window[k] as i32;
                    for (l, v) in h.iter_mut().enumerate() {
                        *v = gamma * (base + l as i32).unsigned_abs() as f32;
                    }
                    let cost = &data.cost[p * nu * nv..(p + 1) * nu * nv];
                    dual_message(
                        k,
                        h,
                        cost,
                        scale,
                        nu,
                        &mut node[FROM_DUAL * no..(FROM_DUAL + 1) * no],
                    );
                },
            );
        }
        self.labels_current = false;
    }

    /// One iteration `count` of the BP-S schedule.
    fn iterate(&mut self, count: usize) {
        self.set_messages();
        let k = count % 2;
        let forward = count % 4 < 2;
        let dual = count % 8 < 4;
        // The sweep rewrites every label of layer k, and of the other layer
        // when it sends the inter-layer messages.
        self.labels_current |= dual;
        let w = self.space.width;
        let n = [self.space.states(0), self.space.states(1)];
        let sweep = Sweep {
            space: self.space,
            data: self.data,
            weights: self.weights,
            edges: self.edges,
            k,
            forward,
            dual,
            spans: &self.spans,
        };
        let [m0, m1] = &mut self.msgs;
        let [l0, l1] = &mut self.labels;
        let (mk, mo, lk, lo) = if k == 0 {
            (m0, m1, l0, l1)
        } else {
            (m1, m0, l1, l0)
        };
        let strips = self.strips.clone();
        let outboxes: Vec<Vec<f32>> = {
            let smk = split_strips(mk, &strips, w * SLOTS * n[k]);
            let smo = split_strips(mo, &strips, w * SLOTS * n[1 - k]);
            let slk = split_strips(lk, &strips, w);
            let slo = split_strips(lo, &strips, w);
            smk.into_par_iter()
                .zip(smo)
                .zip(slk.into_par_iter().zip(slo))
                .zip(strips.par_iter())
                .map(|(((mk, mo), (lk, lo)), &(y0, y1))| {
                    sweep.strip_dispatch(StripRows {
                        y0,
                        y1,
                        mk,
                        mo,
                        lk,
                        lo,
                    })
                })
                .collect()
        };
        // Deliver the messages that crossed a strip boundary, and refresh the
        // labels of the rows that received them.
        let nk = n[k];
        let mut refreshed = Vec::new();
        for (i, outbox) in outboxes.iter().enumerate() {
            let (y0, y1) = strips[i];
            let (row, slot, from) = if forward {
                if i + 1 == strips.len() {
                    continue;
                }
                (y1, FROM_UP, y1 - 1)
            } else {
                if i == 0 {
                    continue;
                }
                (y0 - 1, FROM_DOWN, y0)
            };
            // Only the swept nodes of the sending row sent a message.
            let (xa, xb) = self.spans[from];
            for x in xa..xb {
                let dst = ((row * w + x) * SLOTS + slot) * nk;
                mk[dst..dst + nk].copy_from_slice(&outbox[x * nk..(x + 1) * nk]);
            }
            refreshed.push(row);
        }
        let mut buf = [0f32; MAX_STATES];
        for row in refreshed {
            for p in row * w..(row + 1) * w {
                self.belief(k, p, &mut buf);
                self.labels[k][p] = argmin(&buf[..nk]);
            }
        }
    }

    /// Beliefs of layer `k` at pixel `p`: range term plus every incoming message (once a step
    /// has set the messages).
    #[inline]
    fn belief(&self, k: usize, p: usize, out: &mut [f32]) {
        match self.space.states(k) {
            3 => self.belief_of::<3>(k, p, out),
            5 => self.belief_of::<5>(k, p, out),
            9 => self.belief_of::<9>(k, p, out),
            21 => self.belief_of::<21>(k, p, out),
            _ => self.belief_of::<0>(k, p, out),
        }
    }

    /// [`Self::belief`] with `N` states known at compile time (0: read them from the label
    /// space). Slot after slot, each label's sum in the same order as the sweeps' (range term,
    /// then the messages from the left, right, up, down and the other layer).
    #[inline(always)]
    fn belief_of<const N: usize>(&self, k: usize, p: usize, out: &mut [f32]) {
        let n = if N > 0 { N } else { self.space.states(k) };
        let node = &self.msgs[k][p * SLOTS * n..(p + 1) * SLOTS * n];
        // The flow of label `l` is `base + l` (`LabelSpace::flow`).
        let base = self.space.offset[k][p] - self.space.window[k] as i32;
        let gamma = self.weights.gamma;
        let out = &mut out[..n];
        for (l, o) in out.iter_mut().enumerate() {
            *o = gamma * (base + l as i32).unsigned_abs() as f32;
        }
        for slot in node.chunks_exact(n) {
            for (o, &m) in out.iter_mut().zip(slot) {
                *o += m;
            }
        }
    }

    /// The argmin of the beliefs of every pixel, per layer, from scratch.
    fn all_labels(&self) -> [Vec<u16>; 2] {
        let area = self.space.width * self.space.height;
        let layer = |k: usize| -> Vec<u16> {
            let n = self.space.states(k);
            (0..area)
                .into_par_iter()
                .map_init(
                    || [0f32; MAX_STATES],
                    |buf, p| {
                        self.belief(k, p, buf);
                        argmin(&buf[..n])
                    },
                )
                .collect()
        };
        [layer(0), layer(1)]
    }

    /// The current labels (argmin of the beliefs), per layer.
    #[must_use]
    pub fn labels(&mut self) -> &[Vec<u16>; 2] {
        self.refresh_labels();
        &self.labels
    }

    /// Per pixel of layer `k`: the belief of the best label that is not the
    /// current one or next to it, minus the belief of the current label (0
    /// when the window has no such label). Large means unambiguous.
    #[must_use]
    pub fn margins(&mut self, k: usize) -> Vec<f32> {
        self.refresh_labels();
        let n = self.space.states(k);
        let labels = &self.labels[k];
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
        self.run_until_stable(iterations, None)
    }

    /// [`DualLayerBp::run`], stopping early once the labels of both layers
    /// have stayed the same for `patience` consecutive iterations (`None`:
    /// never). For levels whose only output is the labels: the messages go
    /// on changing, so margins and sub-pixel offsets would not be the same.
    pub fn run_until_stable(&mut self, iterations: usize, patience: Option<usize>) -> BpOutcome {
        self.refresh_labels();
        let (data, space, weights, edges) = (self.data, self.space, self.weights, self.edges);
        let energy_of = |labels: &[Vec<u16>; 2]| energy_with(data, space, labels, &weights, edges);
        let mut energies = Vec::with_capacity(iterations);
        let mut previous = patience.map(|_| self.labels.clone());
        let mut stable = 0;
        // The labels an iteration left, whose energy is taken beside the next iteration's
        // sweeps: it fills the core that the strips of unequal work leave idle at the end of
        // a sweep. The energies are the same, in the same order.
        let mut pending: Option<[Vec<u16>; 2]> = None;
        let mut spare: [Vec<u16>; 2] = Default::default();
        for count in 0..iterations {
            let last = pending.take();
            let ((), taken) = rayon::join(
                || self.iterate(count),
                || last.map(|labels| (energy_of(&labels), labels)),
            );
            if let Some((e, labels)) = taken {
                energies.push(e);
                spare = labels;
            }
            let mut snapshot = std::mem::take(&mut spare);
            for (s, l) in snapshot.iter_mut().zip(&self.labels) {
                // Copied by both cores, into the room of an earlier snapshot.
                s.clear();
                s.par_extend(l.par_iter().copied());
            }
            pending = Some(snapshot);
            if let (Some(p), Some(prev)) = (patience, previous.as_mut()) {
                if *prev == self.labels {
                    stable += 1;
                    if stable >= p {
                        break;
                    }
                } else {
                    stable = 0;
                    prev.clone_from(&self.labels);
                }
            }
        }
        if let Some(labels) = pending {
            energies.push(energy_of(&labels));
        }
        BpOutcome {
            labels: self.labels.clone(),
            energy: energies,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::dense::sift_flow::energy::energy;

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

    /// The weights of the BP tests on [`problem`].
    fn two_region_weights() -> EnergyWeights {
        EnergyWeights {
            alpha: 20.0,
            d: 200.0,
            gamma: 1.0,
        }
    }

    #[test]
    fn bp_lowers_the_energy_and_recovers_the_labels() {
        let (space, data) = problem(24, 70);
        let weights = two_region_weights();
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

    /// The per-edge path with every edge at `d` is the plain truncation:
    /// same labels and energies; a tight truncation on the edges of the step
    /// between the two regions lowers the energy of the same labelling.
    #[test]
    fn uniform_edge_truncation_is_the_plain_truncation() {
        let (w, h) = (24, 70);
        let (space, data) = problem(w, h);
        let weights = two_region_weights();
        let plain = DualLayerBp::new(&space, &data, weights, 16, 3).run(12);
        let uniform = EdgeTruncation {
            right: vec![weights.d; w * h],
            down: vec![weights.d; w * h],
        };
        let mut bp = DualLayerBp::new(&space, &data, weights, 16, 3);
        bp.truncate_edges(&uniform);
        let edged = bp.run(12);
        assert_eq!(plain.labels, edged.labels);
        assert_eq!(plain.energy, edged.energy);
        let mut step = uniform.clone();
        for y in 0..h {
            step.right[y * w + 11] = 0.25 * weights.d;
        }
        let labels = [plain.labels[0].clone(), plain.labels[1].clone()];
        let e_plain = energy(&data, &space, &labels, &weights);
        let e_step = energy_with(&data, &space, &labels, &weights, Some(&step));
        assert!(e_step < e_plain, "{e_step} vs {e_plain}");
    }

    /// Buffers handed on from a larger solve, still holding its messages, give the same run
    /// as fresh ones, with and without the warm start.
    #[test]
    fn reused_buffers_give_the_same_run() {
        let weights = two_region_weights();
        let (big_space, big_data) = problem(30, 80);
        for hierarchy in [0, 2] {
            let mut first = DualLayerBp::new(&big_space, &big_data, weights, 16, 3);
            first.warm_start(2, 4);
            first.run(6);
            let buffers = first.into_buffers();
            let (space, data) = problem(24, 70);
            let mut fresh = DualLayerBp::new(&space, &data, weights, 16, 3);
            fresh.warm_start(hierarchy, 4);
            let fresh = fresh.run(12);
            let mut bp = DualLayerBp::with_buffers(&space, &data, weights, 16, 3, buffers);
            bp.warm_start(hierarchy, 4);
            let reused = bp.run(12);
            assert_eq!(fresh.labels, reused.labels, "hierarchy {hierarchy}");
            assert_eq!(fresh.energy, reused.energy, "hierarchy {hierarchy}");
        }
    }

    #[test]
    fn reserved_buffers_hold_every_grid_of_the_warm_start() {
        // 10 × 8, then 5 × 4 and 3 × 2; 5 + 3 states; 5 slots; 4 bytes.
        let b = BpBuffers::reserve(10, 8, [5, 3], 2);
        assert_eq!(b.capacity_bytes(), (80 + 20 + 6) * 5 * 8 * 4);
        // A smaller grid keeps the room; a larger layer grows alone.
        let mut grown = b;
        grown.grow(4, 4, [5, 3], 1);
        assert_eq!(grown.capacity_bytes(), (80 + 20 + 6) * 5 * 8 * 4);
        grown.grow(12, 12, [21, 3], 0);
        assert_eq!(
            grown.capacity_bytes(),
            (144 * 21 + 144 * 3 + (20 + 6) * 8) * 5 * 4
        );
    }

    #[test]
    fn active_spans_match_a_dilated_mask() {
        let (w, h) = (23, 17);
        let mut seed = 7u32;
        let mut active = vec![false; w * h];
        for (p, a) in active.iter_mut().enumerate() {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            // A rotated band of real pixels plus scattered ones, a few empty rows.
            let (x, y) = ((p % w) as i32, (p / w) as i32);
            *a = ((3..12).contains(&y) && (x - y).abs() < 6) || (y < 14 && (seed >> 24) < 4);
        }
        for margin in [0usize, 1, 3] {
            let spans = active_spans(&active, w, h, margin);
            for (y, &span) in spans.iter().enumerate() {
                // Naive: every node within `margin` (Chebyshev) of an active one.
                let near: Vec<usize> = (0..w)
                    .filter(|&x| {
                        (0..h).any(|yy| {
                            (0..w).any(|xx| {
                                active[yy * w + xx]
                                    && yy.abs_diff(y) <= margin
                                    && xx.abs_diff(x) <= margin
                            })
                        })
                    })
                    .collect();
                let expected = match (near.first(), near.last()) {
                    (Some(&a), Some(&b)) => (a, b + 1),
                    _ => (0, 0),
                };
                assert_eq!(span, expected, "row {y}, margin {margin}");
            }
        }
    }

    #[test]
    fn nodes_outside_the_spans_send_nothing() {
        let (w, h) = (24, 70);
        let (space, plain) = problem(w, h);
        // A triangle of nodes (a rotated image's empty corner) whose data
        // pulls towards a third flow.
        let outside = |p: usize| (p % w) + (p / w) / 4 < 8;
        let mut misleading = plain.clone();
        let (nu, nv) = (7, 3);
        for p in (0..w * h).filter(|&p| outside(p)) {
            for lv in 0..nv {
                for lu in 0..nu {
                    let du = (lu as i32 - 6).unsigned_abs();
                    misleading.cost[(p * nv + lv) * nu + lu] = (80 * du) as u16;
                }
            }
        }
        let active: Vec<bool> = (0..w * h).map(|p| !outside(p)).collect();
        let spans = active_spans(&active, w, h, 0);
        let weights = two_region_weights();
        let solve = |data: &DataTerm, max_strips: usize, hierarchy: usize| {
            let mut bp = DualLayerBp::new(&space, data, weights, 16, max_strips);
            bp.restrict(spans.clone());
            bp.warm_start(hierarchy, 4);
            bp.run(16).labels
        };
        let inside = |labels: &[Vec<u16>; 2]| -> Vec<[u16; 2]> {
            (0..w * h)
                .filter(|&p| !outside(p))
                .map(|p| [labels[0][p], labels[1][p]])
                .collect()
        };
        for max_strips in [1, 3] {
            // Without the warm start (whose 2 × 2 nodes mix both sides), the
            // nodes inside cannot tell what the nodes outside were given.
            assert_eq!(
                inside(&solve(&plain, max_strips, 0)),
                inside(&solve(&misleading, max_strips, 0)),
                "{max_strips} strips"
            );
            for hierarchy in [0, 2] {
                let labels = solve(&misleading, max_strips, hierarchy);
                let wrong = (0..w * h)
                    .filter(|&p| !outside(p))
                    .filter(|&p| {
                        let truth = if p % w < w / 2 { 2 } else { -1 };
                        space.flow(0, p, usize::from(labels[0][p])) != truth
                            || space.flow(1, p, usize::from(labels[1][p])) != 0
                    })
                    .count();
                assert!(
                    wrong <= w * h / 100,
                    "{max_strips} strips, hierarchy {hierarchy}: {wrong} wrong labels inside"
                );
            }
        }
    }

    #[test]
    fn settled_labels_end_the_run_early_with_the_same_labels() {
        let (space, data) = problem(24, 70);
        let weights = two_region_weights();
        let full = DualLayerBp::new(&space, &data, weights, 16, 1).run(40);
        let mut bp = DualLayerBp::new(&space, &data, weights, 16, 1);
        let early = bp.run_until_stable(40, Some(3));
        assert!(
            early.energy.len() < 40,
            "ran all {} iterations",
            early.energy.len()
        );
        assert_eq!(early.labels, full.labels);
        // The last `patience` iterations left the labels, hence the energy, alone.
        let n = early.energy.len();
        assert!(early.energy[n - 4..].windows(2).all(|e| e[0] == e[1]));
        assert_eq!(early.energy[..], full.energy[..n]);
        // No patience: every iteration runs.
        let mut bp = DualLayerBp::new(&space, &data, weights, 16, 1);
        assert_eq!(bp.run_until_stable(40, None).energy.len(), 40);
    }
}
