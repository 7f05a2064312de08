//! SIFT flow (Liu, Yuen, Torralba, PAMI 2011): dense correspondence by
//! matching dense SIFT descriptors under the energy of eq. (10), minimised by
//! dual-layer belief propagation (BP-S), coarse to fine.
//!
//! [`sift_flow`] matches two arbitrary images (`sdsem flow`); the rectified
//! stereo stage ([`crate::vision::dense`]) drives the same engine with a
//! small vertical window.

pub mod bp;
pub mod energy;
mod params;
pub mod pyramid;
pub mod subpixel;

pub use self::params::{DescriptorPyramid, FlowParams, WarmStartGrids, level_cell_size};
use self::params::{LevelPlan, MIN_STRIP_ROWS};
pub(crate) use self::params::{check_size, min_side};

use std::borrow::Cow;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use self::bp::{BpBuffers, DualLayerBp};
use self::energy::{DataTerm, EnergyWeights, LabelSpace};
use super::error::DenseError;
use crate::vision::Image;
use crate::vision::dense::dense_sift::{
    DenseSiftParams, DescriptorImage, dense_sift, dense_sift_where,
};
use crate::vision::dense::refine::{
    RefineParams, RefinedFlow, refine_flow_to_level, upsample_flow, upsample_refined,
};

/// What one pyramid level did (goes into report.json).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LevelReport {
    /// 0 = full resolution.
    pub level: usize,
    pub width: usize,
    pub height: usize,
    /// Half windows of the u and v layers.
    pub window_u: usize,
    pub window_v: usize,
    /// Dense SIFT cell, pixels of the image the descriptors were computed on
    /// (this level's in the improved mode; full resolution in the paper mode,
    /// whose descriptor images are halved level by level).
    pub cell_size: usize,
    pub iterations: usize,
    /// Energy (10) after every BP iteration (the paper's Fig. 8).
    pub energy: Vec<f64>,
    pub descriptor_ms: f64,
    pub data_term_ms: f64,
    pub bp_ms: f64,
}

/// A dense correspondence from image A to image B: pixel `(x, y)` of A
/// matches `(x + u, y + v)` of B.
#[derive(Debug, Clone)]
pub struct Flow {
    pub u: Image,
    pub v: Image,
    /// Finest level first.
    pub levels: Vec<LevelReport>,
    pub total_ms: f64,
}

impl Flow {
    /// Figures of the flow for report.json (Table 4's v²/u² ratio).
    #[must_use]
    pub fn stats(&self) -> FlowStats {
        FlowStats::of(&self.u, &self.v)
    }
}

/// Summary of a flow field: how vertical it is (paper Table 4 reports the
/// ratio Σv²/Σu² before and after rectification).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FlowStats {
    /// Σv² / Σu² over the finite pixels.
    pub v2_over_u2: f64,
    /// √(mean v²), pixels.
    pub rms_v: f64,
    /// √(mean u²), pixels.
    pub rms_u: f64,
}

impl FlowStats {
    /// Over the pixels where both components are finite.
    #[must_use]
    pub fn of(u: &Image, v: &Image) -> Self {
        let (mut su, mut sv, mut n) = (0f64, 0f64, 0usize);
        for (&a, &b) in u.data().iter().zip(v.data()) {
            if a.is_finite() && b.is_finite() {
                su += f64::from(a).powi(2);
                sv += f64::from(b).powi(2);
                n += 1;
            }
        }
        let n = n.max(1) as f64;
        Self {
            v2_over_u2: if su > 0.0 { sv / su } else { f64::NAN },
            rms_v: (sv / n).sqrt(),
            rms_u: (su / n).sqrt(),
        }
    }
}

/// The engine: the parameters and the plan of every level.
#[derive(Debug, Clone)]
pub(crate) struct Engine {
    pub params: FlowParams,
    /// Finest first.
    pub plan: Vec<LevelPlan>,
    /// The finest level BP runs on (0 = full resolution).
    pub finest: usize,
    /// Horizontal displacement the top level's window is centred on, from A
    /// to B, full-resolution pixels (B to A: the opposite); 0 = none.
    pub top_shift: f32,
}

impl Engine {
    /// The engine of `params`; `vertical` as in [`FlowParams::plan`].
    pub(crate) fn new(params: &FlowParams, vertical: Option<(usize, usize)>) -> Self {
        Self {
            params: *params,
            plan: params.plan(vertical),
            finest: params.finest(),
            top_shift: 0.0,
        }
    }

    /// Whether the contrast-sensitive truncation acts at the finest level, whose truncation is `d`.
    fn edge_truncation(&self, d: f32) -> bool {
        self.params.edge_d < d
    }
}

/// The finest level's result of the engine.
pub(crate) struct EngineRun {
    /// Size of the grid of `u`, `v` and `margin` (level `finest` of image A).
    pub width: usize,
    pub height: usize,
    pub u: Vec<f32>,
    pub v: Vec<f32>,
    /// Per pixel, how much worse the second-best distinct u label is than the
    /// best (belief units); large = unambiguous.
    pub margin: Vec<f32>,
    pub levels: Vec<LevelReport>,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The flow of the coarser level and its size.
type Coarser<'f> = (&'f [Vec<f32>; 2], (usize, usize));

/// One level's label space and data term in one direction: all that BP
/// needs of the descriptors.
struct LevelData {
    space: LabelSpace,
    data: DataTerm,
    data_term_ms: f64,
}

/// Runs `forward`, and `backward` beside it when there is one.
fn forward_and_backward<T: Send>(
    forward: impl FnOnce() -> T + Send,
    backward: Option<impl FnOnce() -> T + Send>,
) -> (T, Option<T>) {
    match backward {
        Some(backward) => {
            let (f, b) = rayon::join(forward, backward);
            (f, Some(b))
        }
        None => (forward(), None),
    }
}

/// One direction's state between levels: the flow of the level just solved.
struct Direction {
    flow: [Vec<f32>; 2],
    margin: Vec<f32>,
    reports: Vec<LevelReport>,
}

/// Sizes of both images at every level, finest first: `(w_a, h_a, w_b, h_b)`.
fn level_sizes(a: &Image, b: &Image, levels: usize) -> Vec<(usize, usize, usize, usize)> {
    let mut sizes = vec![(a.width(), a.height(), b.width(), b.height())];
    for l in 1..levels {
        let (wa, ha, wb, hb) = sizes[l - 1];
        sizes.push((
            pyramid::half_size(wa),
            pyramid::half_size(ha),
            pyramid::half_size(wb),
            pyramid::half_size(hb),
        ));
    }
    sizes
}

/// Masks of every level, finest first.
fn mask_pyramid(
    mask: Option<&[bool]>,
    w: usize,
    h: usize,
    levels: usize,
) -> Vec<Option<Vec<bool>>> {
    let mut out = vec![mask.map(<[bool]>::to_vec)];
    let (mut w, mut h) = (w, h);
    for _ in 1..levels {
        let next = out
            .last()
            .and_then(|m| m.as_ref().map(|m| pyramid::halve_mask(m, w, h)));
        out.push(next);
        (w, h) = (pyramid::half_size(w), pyramid::half_size(h));
    }
    out
}

impl Engine {
    /// Runs coarse to fine from `a` to `b` and, when `both` is set, from `b`
    /// to `a` as well (for the left–right check). `valid_a`/`valid_b` mark
    /// usable pixels (row-major); an invalid pixel of the source image has no
    /// data term (its flow comes from its neighbours; beyond
    /// [`ACTIVE_MARGIN`] of a valid one BP leaves it out and it takes the flow
    /// of the nearest swept pixel of its row), one of the target cannot be
    /// matched.
    ///
    /// Level by level, the descriptors of both images are computed once and
    /// serve both directions, which then run at the same time (two sequential
    /// BP sweeps for two cores); only one level's descriptors are alive at once.
    pub(crate) fn run(
        &self,
        a: &Image,
        b: &Image,
        valid_a: Option<&[bool]>,
        valid_b: Option<&[bool]>,
        both: bool,
    ) -> (EngineRun, Option<EngineRun>) {
        let levels = self.plan.len();
        let p = &self.params;
        let sift = DenseSiftParams {
            cell_size: p.cell_size,
        };
        let sizes = level_sizes(a, b, levels);
        let (masks_a, masks_b) = rayon::join(
            || mask_pyramid(valid_a, a.width(), a.height(), levels),
            || mask_pyramid(valid_b, b.width(), b.height(), levels),
        );

        // Halved: descriptors at full resolution, their images blurred and
        // subsampled (reference code). Per level: an image pyramid,
        // descriptors computed on each level. The image pyramid also serves
        // the contrast-sensitive truncation.
        let halved = p.descriptors == DescriptorPyramid::Halved;
        let t0 = Instant::now();
        let mut desc_pyramid: Vec<(DescriptorImage, DescriptorImage)> = Vec::new();
        // Level 0 is the inputs themselves.
        let mut img_pyramid: Vec<(Cow<'_, Image>, Cow<'_, Image>)> = Vec::new();
        if halved {
            desc_pyramid.push(rayon::join(
                || dense_sift(a, &sift),
                || dense_sift(b, &sift),
            ));
            for l in 1..levels {
                let (da, db) = &desc_pyramid[l - 1];
                let next = rayon::join(
                    || pyramid::halve_descriptors(da),
                    || pyramid::halve_descriptors(db),
                );
                desc_pyramid.push(next);
            }
        }
        if !halved || self.edge_truncation(p.finest_d.unwrap_or(p.d)) {
            img_pyramid.push((Cow::Borrowed(a), Cow::Borrowed(b)));
            for l in 1..levels {
                let (ia, ib) = &img_pyramid[l - 1];
                let next = (pyramid::halve_image(ia), pyramid::halve_image(ib));
                img_pyramid.push((Cow::Owned(next.0), Cow::Owned(next.1)));
            }
        }
        let pyramid_ms = ms(t0);

        // The BP messages, reserved once for the largest grids (untouched until used) and reused
        // from level to level. The coarser levels solve both directions at once, one buffer
        // each. The finest level, by far the largest, solves one direction after the other in
        // the forward buffer (its strips keep the cores busy), whose room holds its grids from
        // the start: the coarser levels use the beginning of it, which the finest level reuses,
        // and its warm-start grids serve both directions. Fresh memory costs more than the
        // messages' arithmetic on its first touch (the kernel clears every page).
        let reserve = |buffers: &mut BpBuffers, l: usize, (w, h): (usize, usize)| {
            let plan = &self.plan[l];
            buffers.grow(w, h, plan.window.map(|w| 2 * w + 1), plan.hierarchy);
        };
        let mut buffers_fwd = BpBuffers::default();
        let mut buffers_bwd = BpBuffers::default();
        for (l, &(wa, ha, wb, hb)) in sizes.iter().enumerate().skip(self.finest) {
            reserve(&mut buffers_fwd, l, (wa, ha));
            if both {
                let buffers = if l == self.finest {
                    &mut buffers_fwd
                } else {
                    &mut buffers_bwd
                };
                reserve(buffers, l, (wb, hb));
            }
        }
        let mut fwd: Option<Direction> = None;
        let mut bwd: Option<Direction> = None;
        for l in (self.finest..levels).rev() {
            if l == self.finest {
                // The backward buffer's levels are done (it would sit beside the descriptors).
                buffers_bwd = BpBuffers::default();
            }
            let td = Instant::now();
            // This level's descriptors, owned: they are dropped once its data
            // terms hold what BP needs of them (the halved pyramid's
            // full-resolution pair alone is 256 bytes a canvas pixel).
            let (da, db) = if halved {
                // Built finest first, taken coarsest first.
                desc_pyramid
                    .pop()
                    .expect("one descriptor level per BP level")
            } else {
                let (ia, ib) = &img_pyramid[l];
                let sift = DenseSiftParams {
                    cell_size: self.plan[l].cell_size,
                };
                // Each image's descriptors serve its real pixels only: as
                // the source they have the data term, as the target the
                // others are never matched.
                rayon::join(
                    || dense_sift_where(ia, &sift, masks_a[l].as_deref()),
                    || dense_sift_where(ib, &sift, masks_b[l].as_deref()),
                )
            };
            let descriptor_ms = ms(td) + if l + 1 == levels { pyramid_ms } else { 0.0 };
            let (wa, ha, wb, hb) = sizes[l];
            fn coarse(d: &Option<Direction>, wc_hc: (usize, usize)) -> Option<Coarser<'_>> {
                d.as_ref().map(|d| (&d.flow, wc_hc))
            }
            let up_a = if l + 1 < levels {
                Some((sizes[l + 1].0, sizes[l + 1].1))
            } else {
                None
            };
            let up_b = if l + 1 < levels {
                Some((sizes[l + 1].2, sizes[l + 1].3))
            } else {
                None
            };
            let source = |k: usize| {
                img_pyramid
                    .get(l)
                    .map(|(ia, ib)| if k == 0 { &**ia } else { &**ib })
            };
            let forward = || {
                self.data_term(
                    l,
                    &da,
                    &db,
                    (wa, ha, wb, hb),
                    masks_a[l].as_deref(),
                    masks_b[l].as_deref(),
                    up_a.and_then(|s| coarse(&fwd, s)),
                    self.top_shift,
                )
            };
            let backward = || {
                self.data_term(
                    l,
                    &db,
                    &da,
                    (wb, hb, wa, ha),
                    masks_b[l].as_deref(),
                    masks_a[l].as_deref(),
                    up_b.and_then(|s| coarse(&bwd, s)),
                    -self.top_shift,
                )
            };
            let (f, b) = forward_and_backward(forward, both.then_some(backward));
            // Freed side by side: returning the pages of the finest level's descriptors (tens
            // of MB each) took one core alone.
            rayon::join(|| drop(da), || drop(db));
            let mask_b = masks_b[l].as_deref();
            let mask_a = masks_a[l].as_deref();
            let (f, b) = if l == self.finest {
                // The last solve frees the warm-start grids before its iterations.
                let bf = &mut buffers_fwd;
                let f = self.solve(l, source(0), f, mask_a, descriptor_ms, bf, b.is_none());
                (
                    f,
                    b.map(|b| self.solve(l, source(1), b, mask_b, descriptor_ms, bf, true)),
                )
            } else {
                let (bf, bb) = (&mut buffers_fwd, &mut buffers_bwd);
                forward_and_backward(
                    || self.solve(l, source(0), f, mask_a, descriptor_ms, bf, false),
                    b.map(|b| {
                        move || self.solve(l, source(1), b, mask_b, descriptor_ms, bb, false)
                    }),
                )
            };
            fwd = Some(merge(fwd, f));
            bwd = match (bwd, b) {
                (prev, Some(b)) => Some(merge(prev, b)),
                (prev, None) => prev,
            };
        }
        let (width, height) = (sizes[self.finest].0, sizes[self.finest].1);
        let (width_b, height_b) = (sizes[self.finest].2, sizes[self.finest].3);
        let finish = |d: Direction, (width, height): (usize, usize)| {
            let [u, v] = d.flow;
            let mut reports = d.reports;
            reports.reverse();
            EngineRun {
                width,
                height,
                u,
                v,
                margin: d.margin,
                levels: reports,
            }
        };
        let fwd = fwd.expect("at least one level ran");
        (
            finish(fwd, (width, height)),
            bwd.map(|b| finish(b, (width_b, height_b))),
        )
    }

    /// The label space and data term of one level in one direction, around
    /// the flow of the coarser level (`None` at the top).
    #[allow(clippy::too_many_arguments)]
    fn data_term(
        &self,
        l: usize,
        da: &DescriptorImage,
        db: &DescriptorImage,
        (w, h, w2, h2): (usize, usize, usize, usize),
        mask_a: Option<&[bool]>,
        mask_b: Option<&[bool]>,
        coarser: Option<Coarser<'_>>,
        shift: f32,
    ) -> LevelData {
        let plan = self.plan[l];
        // The shift in this level's pixels (bounded by the image size).
        #[allow(clippy::cast_possible_truncation)]
        let top = (shift / (1u32 << l.min(31)) as f32).round() as i32;
        let offset = match coarser {
            // Top: proportional correspondence when the sizes differ, plus the shift.
            None => [
                (0..w * h)
                    .map(|p| proportional(p % w, w, w2) + top)
                    .collect(),
                (0..w * h).map(|p| proportional(p / w, h, h2)).collect(),
            ],
            Some((flow, (wc, hc))) => [
                pyramid::upsample_offsets(&flow[0], wc, hc, w, h),
                pyramid::upsample_offsets(&flow[1], wc, hc, w, h),
            ],
        };
        let space = LabelSpace {
            width: w,
            height: h,
            window: plan.window,
            offset,
        };
        let tdata = Instant::now();
        let data = DataTerm::compute(da, db, &space, mask_a, mask_b, self.params.t);
        LevelData {
            space,
            data,
            data_term_ms: ms(tdata),
        }
    }

    /// Solves one level in one direction by BP on its data term, in `buffers`; at the finest
    /// level `last` frees the warm-start grids' messages (kept for the next solve otherwise)
    /// before the iterations.
    #[allow(clippy::too_many_arguments)]
    fn solve(
        &self,
        l: usize,
        source: Option<&Image>,
        level: LevelData,
        mask_a: Option<&[bool]>,
        descriptor_ms: f64,
        buffers: &mut BpBuffers,
        last: bool,
    ) -> Direction {
        let plan = self.plan[l];
        let LevelData {
            space,
            data,
            data_term_ms,
        } = level;
        let (w, h) = (space.width, space.height);
        // A stronger smoothness at the finest BP level, and there its own
        // truncation if one is set.
        let p = &self.params;
        let finest = l == self.finest;
        let (alpha, d) = if finest {
            (p.alpha * p.finest_alpha_scale, p.finest_d.unwrap_or(p.d))
        } else {
            (p.alpha, p.d)
        };
        let weights = EnergyWeights {
            alpha,
            d,
            gamma: p.gamma * (1u32 << l.min(31)) as f32,
        };
        let tbp = Instant::now();
        let mut bp = DualLayerBp::with_buffers(
            &space,
            &data,
            weights,
            MIN_STRIP_ROWS,
            p.max_strips,
            std::mem::take(buffers),
        );
        let spans = mask_a.map(|m| bp::active_spans(m, w, h, ACTIVE_MARGIN));
        if let Some(spans) = &spans {
            bp.restrict(spans.clone());
        }
        // Contrast-sensitive truncation at the finest level: the level's own
        // source image says where depth may step.
        let edges =
            match source {
                Some(img) if finest && self.edge_truncation(d) => Some(
                    energy::contrast_truncation(img, d, p.edge_d, p.edge_contrast),
                ),
                _ => None,
            };
        if let Some(e) = &edges {
            bp.truncate_edges(e);
        }
        // The warm start, when it runs, replaces these messages.
        if p.dual_init_from_data && !bp.warm_start_replaces_messages(plan.hierarchy) {
            bp.init_dual_from_data();
        }
        bp.warm_start(plan.hierarchy, p.warm_start_iterations);
        if finest && last {
            bp.release_warm_start_buffers();
        }
        // Coarser levels hand on their labels only: no more iterations once
        // the labels have settled.
        let patience = (p.settle_iterations > 0 && l > self.finest).then_some(p.settle_iterations);
        let outcome = bp.run_until_stable(plan.iterations, patience);
        let bp_ms = ms(tbp);
        let flow = if finest && p.subpixel {
            subpixel::refine(&data, &space, &outcome.labels)
        } else {
            [0, 1].map(|k| {
                (0..w * h)
                    .into_par_iter()
                    .map(|p| space.flow(k, p, usize::from(outcome.labels[k][p])) as f32)
                    .collect()
            })
        };
        let flow = match &spans {
            Some(spans) => flow.map(|f| extend_rows(f, w, spans)),
            None => flow,
        };
        let margin = if l == self.finest {
            bp.margins(0)
        } else {
            Vec::new()
        };
        *buffers = bp.into_buffers();
        Direction {
            flow,
            margin,
            reports: vec![LevelReport {
                level: l,
                width: w,
                height: h,
                window_u: plan.window[0],
                window_v: plan.window[1],
                cell_size: plan.cell_size,
                iterations: outcome.energy.len(),
                energy: outcome.energy,
                descriptor_ms,
                data_term_ms,
                bp_ms,
            }],
        }
    }
}

/// Pixels (of the level) around the valid source pixels that BP sweeps with
/// them; farther ones take the flow of the nearest swept pixel of their row
/// ([`extend_rows`]). The fill has no data term: a wide ring of it only
/// carries the smoothness along the image's border. Measured: on the most
/// oblique simulated canvas (grid 1024×768, `sdsem-eval dense`) RMSE 2.45 /
/// 2.43 / 2.70 / 3.05 / 3.47 % of the relief at margins 2 / 4 / 6 / 12 / 24
/// (3.48 % sweeping the whole canvas), the other 15 cases within 0.1 point;
/// the Potamogeton pairs (`sdsem-eval potamogeton`) lose 0.1–0.3 point of
/// common coverage at 2, up to 0.1 at 4, none from 6.
const ACTIVE_MARGIN: usize = 4;

/// `field` (row-major, width `w`) with every pixel outside its row's span
/// set to the nearest one inside; a row without a span copies the nearest
/// row that has one (the field unchanged when none has).
fn extend_rows(mut field: Vec<f32>, w: usize, spans: &[(usize, usize)]) -> Vec<f32> {
    for (row, &(a, b)) in field.chunks_exact_mut(w).zip(spans) {
        if b > a {
            let (first, last) = (row[a], row[b - 1]);
            row[..a].fill(first);
            row[b..].fill(last);
        }
    }
    let filled: Vec<usize> = (0..spans.len())
        .filter(|&y| spans[y].1 > spans[y].0)
        .collect();
    for y in (0..spans.len()).filter(|&y| spans[y].1 <= spans[y].0) {
        // The nearest filled rows above and below; the upper one on a tie.
        let i = filled.partition_point(|&f| f < y);
        let src = match (i.checked_sub(1).map(|j| filled[j]), filled.get(i)) {
            (Some(up), Some(&down)) if down - y < y - up => down,
            (Some(up), _) => up,
            (None, Some(&down)) => down,
            (None, None) => continue,
        };
        field.copy_within(src * w..(src + 1) * w, y * w);
    }
    field
}

/// The newer level's direction state, keeping the reports of the older ones.
fn merge(prev: Option<Direction>, mut next: Direction) -> Direction {
    if let Some(p) = prev {
        let mut reports = p.reports;
        reports.append(&mut next.reports);
        next.reports = reports;
    }
    next
}

/// Offset that maps coordinate `i` of a side of `n` to the same relative
/// position of a side of `n2` (0 when the sizes agree).
fn proportional(i: usize, n: usize, n2: usize) -> i32 {
    if n == n2 || n < 2 {
        return 0;
    }
    let target = i as f64 * (n2 - 1) as f64 / (n - 1) as f64;
    (target - i as f64).round() as i32
}

/// Dense SIFT flow from `a` to `b` (two arbitrary images, no rectification).
///
/// # Errors
/// [`DenseError::InvalidParameter`] for unusable parameters,
/// [`DenseError::TooSmall`] when an image is too small for the pyramid.
pub fn sift_flow(a: &Image, b: &Image, params: &FlowParams) -> Result<Flow, DenseError> {
    params.validate()?;
    check_size(a.width(), a.height(), params.levels)?;
    check_size(b.width(), b.height(), params.levels)?;
    let t0 = Instant::now();
    let a = fill_non_finite(a);
    let b = fill_non_finite(b);
    let engine = Engine::new(params, None);
    let (run, _) = engine.run(&a, &b, None, None, false);
    let (w, h) = a.dimensions();
    let levels = run.levels.clone();
    let full = to_full_resolution(
        &a,
        &b,
        None,
        None,
        run,
        engine.finest,
        0,
        params.refinement(),
    );
    Ok(Flow {
        u: Image::from_vec(w, h, full.u).expect("flow has the size of image A"),
        v: Image::from_vec(w, h, full.v).expect("flow has the size of image A"),
        levels,
        total_ms: ms(t0),
    })
}

/// The engine's flow (at level `finest`) carried to the full resolution of
/// `a`: refined on the intensities through the pyramid down to level `stop`
/// when `refine` is given, then upsampled bilinearly. `ncc` is 1 and nothing
/// is clamped without a refinement.
#[allow(clippy::too_many_arguments)]
pub(crate) fn to_full_resolution(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    run: EngineRun,
    finest: usize,
    stop: usize,
    refine: Option<&RefineParams>,
) -> RefinedFlow {
    let (r, level) = to_level(a, b, valid_a, valid_b, run, finest, stop, refine);
    upsample_refined(r, a.dimensions(), level)
}

/// [`to_full_resolution`] before the upsampling of a refined flow: the flow and the pyramid
/// level of `a` it is on (`stop` when refined, 0 otherwise); [`upsample_refined`] finishes.
#[allow(clippy::too_many_arguments)]
pub(crate) fn to_level(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    run: EngineRun,
    finest: usize,
    stop: usize,
    refine: Option<&RefineParams>,
) -> (RefinedFlow, usize) {
    if let Some(params) = refine {
        let stop = stop.min(finest);
        let r = refine_flow_to_level(
            a,
            b,
            valid_a,
            valid_b,
            (&run.u, &run.v),
            finest,
            stop,
            params,
        );
        return (r, stop);
    }
    let (mut u, mut v) = (run.u, run.v);
    let mut size = (run.width, run.height);
    let mut sizes = vec![a.dimensions()];
    for _ in 0..finest {
        let &(w, h) = sizes.last().expect("not empty");
        sizes.push((pyramid::half_size(w), pyramid::half_size(h)));
    }
    for l in (0..finest).rev() {
        let (wf, hf) = sizes[l];
        u = upsample_flow(&u, size.0, size.1, wf, hf, 2.0);
        v = upsample_flow(&v, size.0, size.1, wf, hf, 2.0);
        size = (wf, hf);
    }
    let n = u.len();
    (
        RefinedFlow {
            u,
            v,
            ncc: vec![1.0; n],
            clamped: vec![false; n],
        },
        0,
    )
}

/// Replaces non-finite samples by the nearest finite one on the same row (or
/// the image mean when a row has none), so that no false edge enters a descriptor.
pub(crate) fn fill_non_finite(img: &Image) -> Image {
    let mut out = img.clone();
    fill_non_finite_in_place(&mut out);
    out
}

/// [`fill_non_finite`] in place: a sample is filled from finite ones only, which stay as they are.
pub(crate) fn fill_non_finite_in_place(img: &mut Image) {
    if img.data().iter().all(|v| v.is_finite()) {
        return;
    }
    let w = img.width();
    // The mean fills rows without a finite sample only: summed when there is one.
    let row_without = img
        .data()
        .chunks_exact(w)
        .any(|row| !row.iter().any(|v| v.is_finite()));
    let mean = if row_without {
        let (sum, n) = img
            .data()
            .iter()
            .filter(|v| v.is_finite())
            .fold((0f64, 0usize), |(s, n), &v| (s + f64::from(v), n + 1));
        if n == 0 { 0.0 } else { (sum / n as f64) as f32 }
    } else {
        0.0
    };
    // Rows on every core: each is filled from its own samples (or the mean).
    img.data_mut().par_chunks_mut(w).for_each_init(
        || vec![None; w],
        |left, row| {
            let mut last = None;
            for x in 0..w {
                if row[x].is_finite() {
                    last = Some(x);
                }
                left[x] = last;
            }
            let mut next = None;
            for x in (0..w).rev() {
                if row[x].is_finite() {
                    next = Some(x);
                    continue;
                }
                row[x] = match (left[x], next) {
                    (Some(l), Some(r)) => row[if x - l <= r - x { l } else { r }],
                    (Some(l), None) => row[l],
                    (None, Some(r)) => row[r],
                    (None, None) => mean,
                };
            }
        },
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::Preset;

    /// Filling in place reads finite samples only: the nearest on the row (the left one on a
    /// tie), the mean of the image on a row without any, as a search from the source does.
    #[test]
    fn filling_in_place_takes_the_nearest_finite_sample_of_the_row() {
        let (w, h) = (7, 4);
        let img = Image::from_fn(w, h, |x, y| match (x, y) {
            (0 | 3 | 4, 0) | (1..=5, 1) | (_, 2) | (6, 3) => f32::NAN,
            _ => (10 * y + x) as f32,
        });
        let finite: Vec<f32> = img
            .data()
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .collect();
        let mean = finite.iter().map(|&v| f64::from(v)).sum::<f64>() / finite.len() as f64;
        let reference = Image::from_fn(w, h, |x, y| {
            let row = img.row(y);
            if row[x].is_finite() {
                return row[x];
            }
            (1..w)
                .flat_map(|d| [x.checked_sub(d), Some(x + d)])
                .flatten()
                .find(|&i| i < w && row[i].is_finite())
                .map_or(mean as f32, |i| row[i])
        });
        let filled = fill_non_finite(&img);
        assert_eq!(filled.data(), reference.data());
        assert_eq!(filled.row(0), &[1.0, 1.0, 2.0, 2.0, 5.0, 5.0, 6.0]);
        let mut in_place = img.clone();
        fill_non_finite_in_place(&mut in_place);
        assert_eq!(in_place, filled);
    }

    #[test]
    fn fields_extend_from_the_nearest_swept_pixel() {
        let w = 5;
        let spans = [(0, 0), (1, 3), (0, 0), (0, 0), (2, 5), (0, 0)];
        let field: Vec<f32> = (0..w * spans.len()).map(|p| p as f32).collect();
        let out = extend_rows(field, w, &spans);
        let row = |y: usize| &out[y * w..(y + 1) * w];
        assert_eq!(row(1), &[6.0, 6.0, 7.0, 7.0, 7.0]);
        assert_eq!(row(4), &[22.0, 22.0, 22.0, 23.0, 24.0]);
        // Empty rows copy the nearest row with a span (the upper one on a tie).
        assert_eq!(row(0), row(1));
        assert_eq!(row(2), row(1));
        assert_eq!(row(3), row(4));
        assert_eq!(row(5), row(4));
        // No span at all: unchanged.
        let field = vec![1.0, 2.0, 3.0, 4.0];
        assert_eq!(extend_rows(field.clone(), 2, &[(0, 0), (0, 0)]), field);
    }

    #[test]
    fn every_level_searches_its_own_window() {
        let windows = |p: &FlowParams, k: usize| -> Vec<usize> {
            p.plan(Some((1, 2))).iter().map(|l| l.window[k]).collect()
        };
        // Level 0 (below the finest BP level), 1 (the finest), 2, 3 (top).
        let improved = FlowParams::default();
        assert_eq!(windows(&improved, 0), vec![2, 2, 4, 10]);
        assert_eq!(windows(&improved, 1), vec![1, 1, 1, 2]);
        let paper = FlowParams::preset(Preset::Paper);
        assert_eq!(windows(&paper, 0), vec![2, 2, 2, 10]);
        let as_u: Vec<usize> = paper.plan(None).iter().map(|l| l.window[1]).collect();
        assert_eq!(
            as_u,
            vec![2, 2, 2, 10],
            "no vertical windows: v searches as u"
        );
        let set = FlowParams {
            middle_window: 3,
            ..improved
        };
        assert_eq!(windows(&set, 0)[2], 3);
        let too_wide = FlowParams {
            middle_window: 64,
            ..improved
        };
        assert!(matches!(
            too_wide.validate(),
            Err(DenseError::InvalidParameter { name: "window", .. })
        ));
    }

    /// The multigrid start descends a fixed number of grids below every
    /// level, or (the reference code) down to the top level's resolution.
    #[test]
    fn warm_start_grids_are_fixed_or_reach_the_top() {
        let grids =
            |p: &FlowParams| -> Vec<usize> { p.plan(None).iter().map(|l| l.hierarchy).collect() };
        assert_eq!(grids(&FlowParams::default()), vec![3, 3, 3, 2]);
        assert_eq!(grids(&FlowParams::preset(Preset::Paper)), vec![3, 2, 1, 2]);
    }

    #[test]
    fn per_level_descriptors_keep_the_cells_extent() {
        let cells =
            |p: &FlowParams| -> Vec<usize> { p.plan(None).iter().map(|l| l.cell_size).collect() };
        // Finest BP level 1: levels 0 and 1 keep the cell, coarser ones halve it.
        let two = FlowParams::default();
        assert_eq!(two.cell_size, 2);
        assert_eq!(cells(&two), vec![2, 2, 1, 1]);
        // 3 / 2 rounds to 2, 3 / 4 to 1.
        let three = FlowParams {
            cell_size: 3,
            ..two
        };
        assert_eq!(cells(&three), vec![3, 3, 2, 1]);
        let eight_at_full = FlowParams {
            cell_size: 8,
            finest_level: 0,
            ..two
        };
        assert_eq!(cells(&eight_at_full), vec![8, 4, 2, 1]);
        let fixed = FlowParams {
            keep_cell_extent: false,
            ..two
        };
        assert_eq!(cells(&fixed), vec![2, 2, 2, 2]);
        // The halved pyramid halves descriptor images, not cells.
        let halved = FlowParams {
            descriptors: DescriptorPyramid::Halved,
            ..two
        };
        assert_eq!(cells(&halved), vec![2, 2, 2, 2]);
    }

    /// Smooth random texture (sum of a few hundred random blobs).
    pub(crate) fn texture(w: usize, h: usize, seed: u64) -> Image {
        let mut s = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
        let mut rnd = move || {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let blobs: Vec<(f64, f64, f64, f64)> = (0..(w * h / 40).max(20))
            .map(|_| {
                (
                    rnd() * w as f64,
                    rnd() * h as f64,
                    1.0 + 3.0 * rnd(),
                    rnd() - 0.5,
                )
            })
            .collect();
        let mut img = Image::zeros(w, h);
        for &(cx, cy, r, a) in &blobs {
            let (x0, x1) = (
                (cx - 3.0 * r).max(0.0) as usize,
                ((cx + 3.0 * r) as usize).min(w - 1),
            );
            let (y0, y1) = (
                (cy - 3.0 * r).max(0.0) as usize,
                ((cy + 3.0 * r) as usize).min(h - 1),
            );
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let d2 = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / (r * r);
                    let v = img.get(x, y) + (a * (-d2 / 2.0).exp()) as f32;
                    img.set(x, y, v);
                }
            }
        }
        img.map(|v| 0.5 + 0.5 * v)
    }

    /// `finest_alpha_scale`, `finest_d` and `edge_d` change the finest BP
    /// level only: the coarser levels run the same BP.
    #[test]
    fn the_finest_alpha_scale_and_truncation_act_on_the_finest_level_only() {
        let (w, h) = (64, 48);
        // Unrelated images: the flow is noise, so the smoothness term is not 0.
        let a = texture(w, h, 3);
        let b = texture(w, h, 4);
        // Every level's energies, finest first, on three levels.
        let run = |params: FlowParams| -> Vec<Vec<f64>> {
            let params = FlowParams {
                levels: 3,
                ..params
            };
            sift_flow(&a, &b, &params)
                .unwrap()
                .levels
                .into_iter()
                .map(|l| l.energy)
                .collect()
        };
        let energies = |scale: f32| {
            run(FlowParams {
                finest_alpha_scale: scale,
                ..FlowParams::default()
            })
        };
        let (one, four) = (energies(1.0), energies(4.0));
        // Finest first.
        assert_ne!(one[0], four[0], "the finest level must change");
        assert_eq!(one[1..], four[1..], "coarser levels must not change");
        // `finest_d` likewise, none = `d`.
        let truncated = |finest_d: Option<f32>| {
            run(FlowParams {
                finest_d,
                ..FlowParams::default()
            })
        };
        let (loose, tight) = (truncated(None), truncated(Some(2.0 * 255.0)));
        assert_eq!(loose, four, "none must mean `d`");
        assert_ne!(loose[0], tight[0], "the finest level must change");
        assert_eq!(loose[1..], tight[1..], "coarser levels must not change");
        // `edge_d` likewise; at or above the finest level's `d` it is off.
        let edged = |edge_d: f32| {
            run(FlowParams {
                edge_d,
                ..FlowParams::default()
            })
        };
        let d = FlowParams::default().d;
        let (off, on) = (edged(d), edged(255.0));
        assert_eq!(off, edged(f32::INFINITY));
        assert_ne!(off[0], on[0], "the finest level must change");
        assert_eq!(off[1..], on[1..], "coarser levels must not change");
        for (name, bad) in [
            (
                "edge_d",
                FlowParams {
                    edge_d: f32::NAN,
                    ..FlowParams::default()
                },
            ),
            (
                "edge_contrast",
                FlowParams {
                    edge_contrast: 0.0,
                    ..FlowParams::default()
                },
            ),
        ] {
            assert!(
                matches!(bad.validate(), Err(DenseError::InvalidParameter { name: n, .. }) if n == name),
                "{name}"
            );
        }
        let bad_d = FlowParams {
            finest_d: Some(-1.0),
            ..FlowParams::default()
        };
        assert!(matches!(
            bad_d.validate(),
            Err(DenseError::InvalidParameter {
                name: "finest_d",
                ..
            })
        ));
        let bad = FlowParams {
            finest_alpha_scale: f32::NAN,
            ..FlowParams::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(DenseError::InvalidParameter {
                name: "finest_alpha_scale",
                ..
            })
        ));
    }

    #[test]
    fn recovers_a_global_shift() {
        let (w, h) = (96, 80);
        let big = texture(w + 20, h + 20, 5);
        let a = Image::from_fn(w, h, |x, y| big.get(x + 10, y + 10));
        // b(x + 3, y − 2) = a(x, y): the flow is (3, −2).
        let b = Image::from_fn(w, h, |x, y| big.get(x + 7, y + 12));
        for mode in [Preset::Paper, Preset::Improved] {
            let params = FlowParams {
                levels: 3,
                cell_size: 3,
                ..FlowParams::preset(mode)
            };
            let f = sift_flow(&a, &b, &params).unwrap();
            // Finest first: BP levels 1 and 2 (improved), 0 to 2 (paper).
            let cells: Vec<usize> = f.levels.iter().map(|l| l.cell_size).collect();
            let expected = match mode {
                Preset::Paper => vec![3, 3, 3],
                Preset::Improved => vec![3, 2],
            };
            assert_eq!(cells, expected, "{mode:?}");
            let good = (10..h - 10)
                .flat_map(|y| (10..w - 10).map(move |x| (x, y)))
                .filter(|&(x, y)| {
                    (f.u.get(x, y) - 3.0).abs() < 0.25 && (f.v.get(x, y) + 2.0).abs() < 0.25
                })
                .count();
            let total = (w - 20) * (h - 20);
            assert!(
                good * 100 >= 98 * total,
                "{mode:?}: {good} of {total} correct; u(40,40) = {}, v = {}",
                f.u.get(40, 40),
                f.v.get(40, 40)
            );
        }
    }
}
