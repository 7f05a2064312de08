//! `sdsem flow A B --out FLOW.flo`: dense SIFT-flow correspondence of two
//! arbitrary images (no rectification), written as Middlebury `.flo` (DESIGN §4).

use std::path::Path;

use anyhow::Context;

use crate::export::atomic::OutputDir;
use crate::export::flo;
use crate::vision::dense::sift_flow::{Flow, FlowParams, sift_flow};

/// Loads `a` and `b`, computes the SIFT flow from `a` to `b` and writes it as `name` in
/// `out` (prepared by [`super::output::prepare_file`]), atomically.
///
/// # Errors
/// When an image cannot be read, the flow fails (e.g. an image too small for
/// the pyramid) or the file cannot be written; the message names the file.
pub fn run(
    a: &Path,
    b: &Path,
    (out, name): (&OutputDir, &str),
    params: &FlowParams,
) -> anyhow::Result<Flow> {
    let ia = crate::imaging::file::load_luma(a)?;
    let ib = crate::imaging::file::load_luma(b)?;
    let flow = sift_flow(&ia, &ib, params)
        .with_context(|| format!("SIFT flow from {} to {}", a.display(), b.display()))?;
    out.write(name, |w| {
        flo::write(w, &flow.u, &flow.v).map_err(std::io::Error::other)
    })?;
    Ok(flow)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::Image;

    #[test]
    fn writes_a_flo_file_that_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let tex = crate::testing::Texture::new(8);
        let a = Image::from_fn(64, 48, |x, y| tex.at(x as f64, y as f64) as f32);
        let b = Image::from_fn(64, 48, |x, y| tex.at(x as f64 - 2.0, y as f64) as f32);
        for (name, img) in [("a.png", &a), ("b.png", &b)] {
            image::GrayImage::from_raw(64, 48, img.to_u8())
                .unwrap()
                .save(dir.path().join(name))
                .unwrap();
        }
        let out = dir.path().join("flow.flo");
        let params = FlowParams {
            levels: 2,
            ..FlowParams::default()
        };
        let (prepared, name) = crate::app::output::prepare_file(&out, false).unwrap();
        let flow = run(
            &dir.path().join("a.png"),
            &dir.path().join("b.png"),
            (&prepared, &name),
            &params,
        )
        .unwrap();
        let (u, v) = flo::read(std::fs::File::open(&out).unwrap()).unwrap();
        assert_eq!(u, flow.u);
        assert_eq!(v, flow.v);
        // b(x) = a(x − 2): pixel x of a is found at x + 2 of b.
        assert!((u.get(30, 24) - 2.0).abs() < 0.3, "u = {}", u.get(30, 24));
        assert!(
            run(
                &dir.path().join("missing.png"),
                &dir.path().join("b.png"),
                (&prepared, &name),
                &params
            )
            .is_err()
        );
    }
}
