use super::trace::{Tilt, trace, trace_naive};
use super::*;
use crate::pose::StagePose;
use crate::scene::noise::{mix64, unit};
use crate::scene::{SceneKind, SceneParams};
use crate::walk::WalkParams;

fn scene(kind: SceneKind, seed: u64) -> Scene {
    Scene::generate(&SceneParams {
        kind,
        seed: Some(seed),
        field_um: 60.0,
        sample_um: 0.1,
    })
    .unwrap()
}

fn small_view(tilt_deg: f64) -> View {
    View {
        width: 192,
        height: 160,
        pixel_size_um: 0.1,
        tilt_deg,
        ..View::default()
    }
}

fn clean(scene: &Scene, view: &View) -> Vec<f32> {
    render(scene, view, &ShadingParams::default())
}

/// Normalised cross-correlation of two equal-length samples.
fn ncc(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt().max(1e-12)
}

fn patch(img: &[f32], w: usize, cx: isize, cy: isize, r: isize) -> Vec<f64> {
    let mut out = Vec::new();
    for y in cy - r..=cy + r {
        for x in cx - r..=cx + r {
            out.push(f64::from(img[y as usize * w + x as usize]));
        }
    }
    out
}

/// Where the patch of `a` centred at `(cx, cy)` lies in `b`: integer NCC search
/// over ±`range` pixels, then a parabola through the neighbours of the peak.
fn find_shift(
    a: &[f32],
    b: &[f32],
    w: usize,
    cx: isize,
    cy: isize,
    r: isize,
    range: isize,
) -> (f64, f64) {
    let pa = patch(a, w, cx, cy, r);
    let mut best = (f64::NEG_INFINITY, 0, 0);
    let mut scores = std::collections::HashMap::new();
    for dy in -range..=range {
        for dx in -range..=range {
            let c = ncc(&pa, &patch(b, w, cx + dx, cy + dy, r));
            scores.insert((dx, dy), c);
            if c > best.0 {
                best = (c, dx, dy);
            }
        }
    }
    let (_, bx, by) = best;
    let sub = |m: f64, c: f64, p: f64| {
        let d = m - 2.0 * c + p;
        if d.abs() < 1e-12 {
            0.0
        } else {
            0.5 * (m - p) / d
        }
    };
    let at = |dx, dy| scores.get(&(dx, dy)).copied().unwrap_or(best.0);
    let fx = sub(at(bx - 1, by), best.0, at(bx + 1, by));
    let fy = sub(at(bx, by - 1), best.0, at(bx, by + 1));
    (bx as f64 + fx, by as f64 + fy)
}

#[test]
fn fast_trace_agrees_with_the_naive_reference() {
    for (kind, seed) in [
        (SceneKind::Particles, 1),
        (SceneKind::Grid, 2),
        (SceneKind::Rough, 3),
        (SceneKind::Dome, 4),
    ] {
        let sc = scene(kind, seed);
        let mut h = mix64(seed);
        let mut hits = 0;
        for _ in 0..3000 {
            h = mix64(h);
            let t = (unit(h) - 0.5) * 120.0;
            h = mix64(h);
            let s = (unit(h) - 0.5) * 64.0;
            h = mix64(h);
            let v = (unit(h) - 0.5) * 64.0;
            let tilt = Tilt::from_deg(t);
            let fast = trace(&sc, s, v, tilt);
            let slow = trace_naive(&sc, s, v, tilt);
            match (fast, slow) {
                (Some(a), Some(b)) => {
                    hits += 1;
                    assert_eq!(a.facet, b.facet);
                    assert!(
                        (a.r - b.r).abs() < 1e-9 && (a.z - b.z).abs() < 1e-9,
                        "{kind} t={t}: {a:?} vs {b:?}"
                    );
                }
                (None, None) => {}
                other => panic!("{kind} t={t} s={s} v={v}: {other:?}"),
            }
        }
        assert!(hits > 2000, "{kind}: too few hits {hits}");
    }
}

#[test]
fn traced_points_lie_on_the_surface_and_on_their_ray() {
    let sc = scene(SceneKind::Grid, 5);
    let view = View {
        tilt_axis_deg: 25.0,
        scan_rotation_deg: 2.0,
        ..small_view(12.0)
    };
    for (k, p) in visible_points(&sc, &view).iter().enumerate() {
        let p = p.expect("the field covers the frame");
        if p.facet == Facet::Top {
            assert!((sc.height_at(p.s, p.r).unwrap() - p.z).abs() < 1e-6);
        }
        let (x, y) = view.project(&p);
        assert!(
            (x - (k % view.width) as f64).abs() < 1e-8
                && (y - (k / view.width) as f64).abs() < 1e-8
        );
    }
}

#[test]
fn raised_point_moves_along_n_by_h_sin_theta() {
    // Projection alone, DESIGN §3: φ = 30°, θ = 6°.
    let phi: f64 = 30.0;
    let theta: f64 = 6.0;
    let left = View {
        tilt_axis_deg: phi,
        ..small_view(0.0)
    };
    let right = View {
        tilt_deg: theta,
        ..left
    };
    let h = 10.0;
    let low = SurfacePoint {
        s: 1.0,
        r: 0.0,
        z: 0.0,
        facet: Facet::Top,
    };
    let high = SurfacePoint { z: h, ..low };
    let d = |v: &View| {
        let (a, b) = (v.project(&high), v.project(&low));
        (a.0 - b.0, a.1 - b.1)
    };
    let (d0, d1) = (d(&left), d(&right));
    let expect = h * theta.to_radians().sin() / left.pixel_size_um;
    let n = (-phi.to_radians().sin(), phi.to_radians().cos());
    assert!((d1.0 - d0.0 - expect * n.0).abs() < 1e-9);
    assert!((d1.1 - d0.1 - expect * n.1).abs() < 1e-9);
}

#[test]
fn rendered_relief_moves_the_documented_way() {
    // Image evidence, independent of the ground-truth code: the top of a dome
    // shifts relative to the substrate by h·sin θ along n = (0, 1) for φ = 0.
    let sc = Scene::generate(&SceneParams {
        kind: SceneKind::Dome,
        seed: Some(3),
        field_um: 80.0,
        sample_um: 0.1,
    })
    .unwrap();
    let theta: f64 = 6.0;
    let left = View {
        width: 320,
        height: 320,
        pixel_size_um: 0.2,
        ..small_view(0.0)
    };
    let right = View {
        tilt_deg: theta,
        ..left
    };
    let (a, b) = (clean(&sc, &left), clean(&sc, &right));
    let heights = height_map(&sc, &left);
    let w = left.width;
    // The highest and the lowest smooth patches (no particle edges in them).
    let mut top = (f32::NEG_INFINITY, 0);
    let mut low = (f32::INFINITY, 0);
    for y in (40..280).step_by(4) {
        for x in (40..280).step_by(4) {
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for yy in y - 12..=y + 12 {
                for xx in x - 12..=x + 12 {
                    lo = lo.min(heights[yy * w + xx]);
                    hi = hi.max(heights[yy * w + xx]);
                }
            }
            if hi - lo > 1.5 {
                continue;
            }
            let z = heights[y * w + x];
            if z > top.0 {
                top = (z, y * w + x);
            }
            if z < low.0 {
                low = (z, y * w + x);
            }
        }
    }
    let at = |k: usize| ((k % w) as isize, (k / w) as isize);
    let (tx, ty) = at(top.1);
    let (lx, ly) = at(low.1);
    let st = find_shift(&a, &b, w, tx, ty, 12, 24);
    let sl = find_shift(&a, &b, w, lx, ly, 12, 24);
    let expect = f64::from(top.0 - low.0) * theta.to_radians().sin() / left.pixel_size_um;
    assert!(expect > 8.0, "relief too small for the test: {expect}");
    assert!((st.0 - sl.0).abs() < 0.5, "moved across n: {st:?} {sl:?}");
    assert!(
        (st.1 - sl.1 - expect).abs() < 0.1 * expect,
        "parallax {} px, expected {expect}",
        st.1 - sl.1
    );
}

#[test]
fn stage_pan_and_walk_move_the_image_as_documented() {
    let sc = scene(SceneKind::Particles, 9);
    let optics = OpticsParams {
        width: 192,
        height: 160,
        ..OpticsParams::default()
    };
    let at = |pose: StagePose, walk: [f64; 2]| {
        let view = optics.view(&pose, 192, 160, walk, [0.0, 0.0]);
        clean(&sc, &view)
    };
    let base = at(StagePose::default(), [0.0, 0.0]);
    // Stage +X by 1.5 µm: content moves by −15 px along x.
    let moved = at(
        StagePose {
            x_um: 1.5,
            ..StagePose::default()
        },
        [0.0, 0.0],
    );
    let (dx, dy) = find_shift(&base, &moved, 192, 96, 80, 14, 18);
    assert!(
        (dx + 15.0).abs() < 0.2 && dy.abs() < 0.2,
        "pan X: {dx} {dy}"
    );
    // Stage +Y by 1 µm: −10 px along y.
    let moved = at(
        StagePose {
            y_um: 1.0,
            ..StagePose::default()
        },
        [0.0, 0.0],
    );
    let (dx, dy) = find_shift(&base, &moved, 192, 96, 80, 14, 18);
    assert!(
        dx.abs() < 0.2 && (dy + 10.0).abs() < 0.2,
        "pan Y: {dx} {dy}"
    );
    // A walk of (0.6, −0.3) µm moves the content by (6, −3) px.
    let walked = at(StagePose::default(), [0.6, -0.3]);
    let (dx, dy) = find_shift(&base, &walked, 192, 96, 80, 14, 18);
    assert!(
        (dx - 6.0).abs() < 0.2 && (dy + 3.0).abs() < 0.2,
        "walk: {dx} {dy}"
    );
    // The walk model feeds the same offset: 5 px/° of 0.1 µm pixels.
    let w = WalkParams {
        px_per_deg: 5.0,
        direction_deg: 0.0,
        random_px: 0.0,
        ..WalkParams::default()
    };
    let v = optics.view(
        &StagePose {
            tilt_deg: 2.0,
            ..StagePose::default()
        },
        192,
        160,
        w.offset_um(2.0, optics.pixel_size_um),
        [0.0, 0.0],
    );
    assert!((v.offset_um[0] - 1.0).abs() < 1e-12 && v.offset_um[1].abs() < 1e-12);
}

#[test]
fn pixel_size_scales_with_frame_width() {
    let optics = OpticsParams::default();
    assert!((optics.pixel_size_at(1280) - 0.1).abs() < 1e-12);
    assert!((optics.pixel_size_at(320) - 0.4).abs() < 1e-12);
}

#[test]
fn rendering_is_deterministic_for_a_seed() {
    let a = scene(SceneKind::Rough, 21);
    let b = scene(SceneKind::Rough, 21);
    let view = small_view(5.0);
    let noise = NoiseParams::default();
    let ia = render_noisy(&a, &view, &ShadingParams::default(), &noise, 2.0, 77);
    let ib = render_noisy(&b, &view, &ShadingParams::default(), &noise, 2.0, 77);
    assert_eq!(ia, ib);
    let ic = render_noisy(&b, &view, &ShadingParams::default(), &noise, 2.0, 78);
    assert_ne!(ia, ic);
    let other = render(
        &scene(SceneKind::Rough, 22),
        &view,
        &ShadingParams::default(),
    );
    assert_ne!(clean(&a, &view), other);
}

#[test]
fn noise_falls_with_dwell_like_shot_noise() {
    let sc = scene(SceneKind::Particles, 2);
    let view = small_view(0.0);
    let noise = NoiseParams {
        read_noise: 0.0,
        ..NoiseParams::default()
    };
    let base = clean(&sc, &view);
    let rms = |dwell: f64| {
        let noisy = render_noisy(&sc, &view, &ShadingParams::default(), &noise, dwell, 5);
        let sum: f64 = noisy
            .iter()
            .zip(&base)
            .map(|(a, b)| f64::from(a - b).powi(2))
            .sum();
        (sum / base.len() as f64).sqrt()
    };
    let (fast, slow) = (rms(1.0), rms(16.0));
    let ratio = fast / slow;
    assert!(
        (ratio - 4.0).abs() < 0.3,
        "noise ratio {ratio} for 16× dwell (fast {fast}, slow {slow})"
    );
    assert!(fast > 0.03, "a 1 µs scan should be visibly noisy: {fast}");
}

#[test]
fn steep_grid_walls_hide_the_floor_behind_them() {
    let sc = scene(SceneKind::Grid, 5);
    let left = View {
        width: 256,
        height: 256,
        ..small_view(0.0)
    };
    let right = View {
        tilt_deg: 10.0,
        ..left
    };
    let same = correspondences(&sc, &left, &left);
    assert!(
        same.iter().flatten().all(|c| !c.occluded),
        "a view cannot hide its own points"
    );
    let corr = correspondences(&sc, &left, &right);
    let heights = height_map(&sc, &left);
    let mut occluded = 0;
    for (k, c) in corr.iter().enumerate() {
        let c = c.unwrap();
        if !c.occluded {
            continue;
        }
        occluded += 1;
        // What hides the point stands above it on a bar or its steep wall.
        let q = trace_pixel(&sc, &right, c.x, c.y).unwrap();
        let (gs, gr) = sc.gradient(q.s, q.r);
        let steep = gs.hypot(gr) > 3.0;
        assert!(
            q.z > f64::from(heights[k]) + 0.01,
            "occluder below the point"
        );
        assert!(
            steep || q.z > 8.0,
            "occluder neither a wall nor a bar: {q:?}"
        );
    }
    let fraction = f64::from(occluded) / corr.len() as f64;
    // Walls ~15 µm high at 10° hide a strip ~2.6 µm wide behind each bar
    // facing away from the beam: a few per cent of the floor.
    assert!(
        fraction > 0.01 && fraction < 0.25,
        "occluded fraction {fraction}"
    );
}

#[test]
fn true_correspondences_land_on_matching_image_content() {
    for (kind, seed) in [
        (SceneKind::Particles, 3),
        (SceneKind::Rough, 4),
        (SceneKind::Grid, 6),
    ] {
        let sc = scene(kind, seed);
        let left = View {
            tilt_axis_deg: 20.0,
            ..small_view(-3.0)
        };
        let right = View {
            tilt_deg: 3.0,
            scan_rotation_deg: 1.5,
            ..left
        };
        let (a, b) = (clean(&sc, &left), clean(&sc, &right));
        let corr = correspondences(&sc, &left, &right);
        let exact = agreeing_patches(&a, &b, &left, &corr, (0.0, 0.0));
        assert!(exact > 0.9, "{kind}: only {exact} of patches agree");
        // The test has power: correspondences off by a pixel and a half fail it.
        let off = agreeing_patches(&a, &b, &left, &corr, (1.1, 1.1));
        assert!(
            off < exact - 0.35,
            "{kind}: {off} of patches agree even off by 1.5 px"
        );
    }
}

/// Share of 11 × 11 patches of `a` whose pixels, looked up in `b` at their
/// correspondences (+ `offset`), correlate above 0.9.
fn agreeing_patches(
    a: &[f32],
    b: &[f32],
    view: &View,
    corr: &[Option<Correspondence>],
    offset: (f64, f64),
) -> f64 {
    let w = view.width;
    let r = 5usize;
    let (mut good, mut total) = (0, 0);
    for cy in (r..view.height - r).step_by(9) {
        for cx in (r..w - r).step_by(9) {
            let mut pa = Vec::new();
            let mut pb = Vec::new();
            for y in cy - r..=cy + r {
                for x in cx - r..=cx + r {
                    let Some(c) = corr[y * w + x].filter(Correspondence::is_visible) else {
                        continue;
                    };
                    let Some(vb) = sample(b, w, view.height, c.x + offset.0, c.y + offset.1) else {
                        continue;
                    };
                    pa.push(f64::from(a[y * w + x]));
                    pb.push(vb);
                }
            }
            if pa.len() < (2 * r + 1).pow(2) {
                continue;
            }
            total += 1;
            if ncc(&pa, &pb) > 0.9 {
                good += 1;
            }
        }
    }
    assert!(total > 200, "{total} patches");
    f64::from(good) / f64::from(total)
}

fn sample(img: &[f32], w: usize, h: usize, x: f64, y: f64) -> Option<f64> {
    if x < 0.0 || y < 0.0 || x > (w - 1) as f64 || y > (h - 1) as f64 {
        return None;
    }
    let (x0, y0) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let g = |x: usize, y: usize| f64::from(img[y * w + x]);
    let top = g(x0, y0) * (1.0 - fx) + g(x0 + 1, y0) * fx;
    let bottom = g(x0, y0 + 1) * (1.0 - fx) + g(x0 + 1, y0 + 1) * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

#[test]
fn height_map_is_nan_off_the_specimen() {
    let sc = scene(SceneKind::Dome, 1);
    // 100 µm wide frame over a 60 µm field: the margins see nothing.
    let view = View {
        width: 100,
        height: 80,
        pixel_size_um: 1.0,
        ..View::default()
    };
    let hm = height_map(&sc, &view);
    assert!(hm[0].is_nan());
    assert!(hm[40 * 100 + 50].is_finite());
    let img = clean(&sc, &view);
    assert!((img[0] - ShadingParams::default().background as f32).abs() < 0.02);
}

#[test]
fn quantisation_clamps_and_rounds() {
    assert_eq!(to_u16(&[-0.1, 0.0, 0.5, 1.2]), vec![0, 0, 32768, 65535]);
    assert_eq!(to_u8(&[0.0, 1.0 / 255.0, 2.0]), vec![0, 1, 255]);
}

/// CPU seconds this process has used (user + system), from /proc; 0 elsewhere.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the command name (which is in parentheses): utime is the 14th field overall.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<f64> = rest
        .split_whitespace()
        .filter_map(|x| x.parse().ok())
        .collect();
    // rest starts at field 3 (state, not numeric, filtered out): utime, stime are fields 14, 15.
    (f.get(10).copied().unwrap_or(0.0) + f.get(11).copied().unwrap_or(0.0)) / 100.0
}

/// Render timings (wall and CPU seconds; on an idle machine wall ≈ CPU / cores):
/// `cargo test -p sdsem-sim --lib render::tests::timings -- --ignored --nocapture`
#[test]
#[ignore = "prints timings"]
fn timings() {
    use std::time::Instant;
    let timed = |f: &mut dyn FnMut()| {
        let (t, c) = (Instant::now(), cpu_seconds());
        f();
        (t.elapsed().as_secs_f64(), cpu_seconds() - c)
    };
    for kind in SceneKind::ALL {
        let mut sc = None;
        let scene_t = timed(&mut || {
            sc = Some(
                Scene::generate(&SceneParams {
                    kind,
                    ..SceneParams::default()
                })
                .unwrap(),
            )
        });
        let sc = sc.unwrap();
        let full = View {
            tilt_deg: 10.0,
            ..View::default()
        };
        let mut img = Vec::new();
        let full_t = timed(&mut || {
            img = render_noisy(
                &sc,
                &full,
                &ShadingParams::default(),
                &NoiseParams::default(),
                10.0,
                1,
            )
        });
        let track = View {
            width: 320,
            height: 240,
            pixel_size_um: 0.4,
            ..full
        };
        let mut reps = 0;
        let track_t = timed(&mut || {
            for _ in 0..10 {
                reps += render_noisy(
                    &sc,
                    &track,
                    &ShadingParams::default(),
                    &NoiseParams::default(),
                    1.0,
                    1,
                )
                .len();
            }
        });
        let truth_t = timed(&mut || {
            let _ = height_map(&sc, &full);
        });
        println!(
            "{kind:9}: scene {:.2} s (cpu {:.2}), 1280×960 {:.3} s (cpu {:.2}), 320×240 {:.4} s (cpu {:.3}), height map 1280×960 {:.3} s (cpu {:.2}); z {:.1}..{:.1} µm; {} threads",
            scene_t.0,
            scene_t.1,
            full_t.0,
            full_t.1,
            track_t.0 / 10.0,
            track_t.1 / 10.0,
            truth_t.0,
            truth_t.1,
            sc.height_range().0,
            sc.height_range().1,
            rayon::current_num_threads()
        );
        assert_eq!(reps, 10 * 320 * 240);
        if let Ok(dir) = std::env::var("SDSEM_SIM_DUMP") {
            let path = format!("{dir}/{kind}.pgm");
            let mut bytes = format!("P5 {} {} 255\n", full.width, full.height).into_bytes();
            bytes.extend(to_u8(&img));
            std::fs::write(&path, bytes).unwrap();
        }
    }
}

/// The calibration grid's bars have walls steeper than half the tilt, so each view sees a wall
/// the other cannot: the bar's outline (its strongest texture) moves by about half the top's
/// parallax, the top's own texture by all of it. A window matcher that straddles the outline
/// measures the bar at about half its height (`sdsem-eval dense --only calgrid`, "tops' relief").
#[test]
fn calgrid_outline_moves_by_half_the_tops_parallax() {
    let sc = scene(SceneKind::Calgrid, 102);
    let theta: f64 = 7.0;
    let left = View {
        width: 400,
        height: 400,
        ..small_view(0.0)
    };
    let right = View {
        tilt_deg: theta,
        ..left
    };
    let (a, b) = (clean(&sc, &left), clean(&sc, &right));
    let heights = height_map(&sc, &left);
    let w = left.width;
    let top = heights.iter().copied().fold(0f32, f32::max);
    // Where a column crosses one bar cleanly: a run of top between floor on both sides.
    let mut ratios_outline = Vec::new();
    let mut ratios_top = Vec::new();
    for x in (30..370).step_by(7) {
        let col = |img: &[f32], y: usize| f64::from(img[y * w + x]);
        let mut y = 30;
        while y < 370 {
            if heights[y * w + x] < 0.95 * top {
                y += 1;
                continue;
            }
            let start = y;
            while y < 370 && heights[y * w + x] >= 0.95 * top {
                y += 1;
            }
            let (len, yc) = (y - start, (start + y) / 2);
            let floor_around =
                heights[(start - 6) * w + x] == 0.0 && heights[(y + 5) * w + x] == 0.0;
            if !(10..=30).contains(&len) || !floor_around || !(40..=360).contains(&yc) {
                continue;
            }
            // The outline: the half-way crossings of the bright bar over the dark floor.
            let edges = |img: &[f32]| {
                let (lo, hi) = (yc - 22, yc + 22);
                let floor = 0.5 * (col(img, lo) + col(img, hi));
                let peak = (lo..hi).map(|k| col(img, k)).fold(f64::MIN, f64::max);
                let t = floor + 0.5 * (peak - floor);
                let cross = |k: usize| {
                    let (p, q) = (col(img, k), col(img, k + 1));
                    k as f64 + (t - p) / (q - p)
                };
                let first = (lo..hi).find(|&k| col(img, k) < t && col(img, k + 1) >= t);
                let last = (lo..hi)
                    .rev()
                    .find(|&k| col(img, k) >= t && col(img, k + 1) < t);
                first.zip(last).map(|(f, l)| 0.5 * (cross(f) + cross(l)))
            };
            let parallax = f64::from(heights[yc * w + x]) * theta.to_radians().sin() / 0.1;
            if let (Some(ea), Some(eb)) = (edges(&a), edges(&b)) {
                ratios_outline.push((eb - ea) / parallax);
                let s = find_shift(&a, &b, w, x as isize, yc as isize, 3, 4);
                ratios_top.push(s.1 / parallax);
            }
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    assert!(
        ratios_outline.len() >= 5,
        "too few clean crossings: {}",
        ratios_outline.len()
    );
    let (outline, tops) = (median(ratios_outline.clone()), median(ratios_top.clone()));
    eprintln!(
        "outline {outline:.3} tops {tops:.3} of the parallax ({} crossings)",
        ratios_outline.len()
    );
    assert!(
        (0.3..0.7).contains(&outline),
        "outline moves {outline:.2} of the parallax"
    );
    assert!(
        (tops - 1.0).abs() < 0.2,
        "top moves {tops:.2} of the parallax"
    );
}
