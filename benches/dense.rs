//! Benchmarks of the dense stage's kernels (criterion). `cargo bench -p sdsem
//! --bench dense`; under `cargo test --benches` each runs once on its input.
//!
//! Inputs are synthetic (value-noise texture, a dome of disparity) at a size
//! where one iteration takes milliseconds, so the figures scale to
//! 1280 × 960 by the pixel count.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use sdsem::eval::synthetic::{Texture, dome, render};
use sdsem::vision::Image;
use sdsem::vision::dense::dense_sift::{DenseSiftParams, dense_sift};
use sdsem::vision::dense::sift_flow::bp::DualLayerBp;
use sdsem::vision::dense::sift_flow::energy::{DataTerm, EnergyWeights, LabelSpace};
use sdsem::vision::dense::{DenseParams, dense_disparity};
use sdsem::vision::filter::bilateral_grid::{BilateralParams, bilateral_filter};

const W: usize = 320;
const H: usize = 240;

fn pair() -> (Image, Image) {
    let p = render(W, H, Texture::new(4), &dome(W, H, 0.0, 6.0, 0.4), 0.2, 0.01);
    (p.left, p.right)
}

fn kernels(c: &mut Criterion) {
    let (a, b) = pair();
    let sift = DenseSiftParams::default();
    c.bench_function("dense_sift 320x240", |bn| {
        bn.iter(|| dense_sift(black_box(&a), &sift))
    });

    let (da, db) = (dense_sift(&a, &sift), dense_sift(&b, &sift));
    for (name, window) in [("u±2 v±1", [2, 1]), ("u±2 v±2", [2, 2])] {
        let space = LabelSpace {
            width: W,
            height: H,
            window,
            offset: [vec![1; W * H], vec![0; W * H]],
        };
        c.bench_function(&format!("data term 320x240 {name}"), |bn| {
            bn.iter(|| DataTerm::compute(black_box(&da), &db, &space, None, None, None))
        });
        let data = DataTerm::compute(&da, &db, &space, None, None, None);
        let weights = EnergyWeights {
            alpha: 510.0,
            d: 10200.0,
            gamma: 1.275,
        };
        c.bench_function(&format!("bp 8 iterations 320x240 {name}"), |bn| {
            bn.iter(|| {
                let mut bp = DualLayerBp::new(&space, &data, weights, 48, 4);
                bp.run(8)
            })
        });
    }

    let (disp, _) = (
        dense_disparity(&a, &b, None, None, &DenseParams::default()).map(|d| d.raw),
        (),
    );
    if let Ok(disp) = disp {
        let params = BilateralParams::default();
        c.bench_function("bilateral grid 320x240", |bn| {
            bn.iter(|| bilateral_filter(black_box(&disp), None, &params))
        });
    }
}

fn stage(c: &mut Criterion) {
    let (a, b) = pair();
    let mut group = c.benchmark_group("dense stage");
    group.sample_size(10);
    group.bench_function("dense_disparity 320x240 improved", |bn| {
        bn.iter(|| dense_disparity(black_box(&a), &b, None, None, &DenseParams::default()))
    });
    group.finish();
}

criterion_group!(benches, kernels, stage);
criterion_main!(benches);
