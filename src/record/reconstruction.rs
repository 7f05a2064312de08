//! What a reconstruction puts in the run record, laid out so Foxglove shows it right:
//!
//! | topic | schema | what a viewer shows |
//! | --- | --- | --- |
//! | `/tf` | foxglove.FrameTransforms | frame `left` in `specimen` (see [`topics::FRAME_LEFT`]) |
//! | `/recon/height` | foxglove.RawImage 32FC1 | the heights, µm, NaN unknown (DESIGN §5) |
//! | `/recon/height_preview` | foxglove.CompressedImage (PNG) | the heights in viridis over their 1st–99th percentile, unknown black |
//! | `/recon/height_preview/legend` | foxglove.ImageAnnotations | the heights of the two end colours |
//! | `/recon/pointcloud` | foxglove.PointCloud | every known height, µm, with the micrograph's intensity |
//! | `/recon/mesh` | foxglove.SceneUpdate | the mesh decimated to ≤ [`MESH_PREVIEW_MAX_VERTICES`] vertices, a glTF model shaded grey by intensity |
//!
//! Units: µm throughout, as DESIGN §5 fixes for the cloud. Foxglove's 3D panel labels its
//! grid in metres and steps its camera settings by millimetres, so one unit there is one
//! micrometre here: in metres a 128 µm field would be 0.000128 units wide, inside the
//! camera's near plane. The full-resolution mesh is `mesh.ply` in the run directory.

use super::entry::Entry;
use super::error::RecordError;
use super::recorder::RecorderHandle;
use super::topics;
use crate::export::preview::HeightPreview;
use crate::export::{MeshParams, glb, ply};
use crate::numbers::fmt_um;
use crate::vision::Image;

/// Most vertices of the `/recon/mesh` model: 16-bit glTF indices, about 1.4 MB for the
/// ~128 000 triangles (a 1280×960 map keeps every 5th pixel of each row and column).
pub const MESH_PREVIEW_MAX_VERTICES: usize = 65_535;

/// A reconstruction to record.
#[derive(Debug, Clone, Copy)]
pub struct ReconstructionView<'a> {
    /// Heights on the left micrograph's grid, µm, NaN unknown.
    pub height_um: &'a Image,
    /// The left micrograph, `[0, 1]`: the cloud's intensity and the mesh's shade.
    pub intensity: &'a Image,
    pub pixel_size_um: f64,
    /// Where the mesh is cut (as for `mesh.ply`).
    pub mesh: &'a MeshParams,
}

impl RecorderHandle {
    /// Records the topics of the module's table, all at `log_time_ns`.
    ///
    /// # Errors
    /// [`RecordError::InvalidMessage`] when `intensity` and `height_um` differ in size or the
    /// preview cannot be encoded, and as [`Self::send`].
    pub fn reconstruction(
        &self,
        log_time_ns: u64,
        view: &ReconstructionView<'_>,
    ) -> Result<(), RecordError> {
        let (w, h) = view.height_um.dimensions();
        if view.intensity.dimensions() != (w, h) {
            return Err(RecordError::InvalidMessage {
                topic: topics::RECON_POINTCLOUD.to_owned(),
                reason: format!(
                    "the intensity image is {}×{}, the height map {w}×{h}",
                    view.intensity.width(),
                    view.intensity.height()
                ),
            });
        }
        let p = view.pixel_size_um;
        // The centre of the left micrograph, at height 0, is the origin of `specimen`.
        let centre = [
            -((w as f64 - 1.0) / 2.0) * p,
            ((h as f64 - 1.0) / 2.0) * p,
            0.0,
        ];
        self.send(Entry::frame_transforms(
            topics::TRANSFORMS,
            log_time_ns,
            &[(topics::FRAME_SPECIMEN, topics::FRAME_LEFT, centre)],
        )?)?;
        self.height(log_time_ns, view.height_um)?;

        let preview = HeightPreview::new(view.height_um);
        let png = preview.png().map_err(|e| RecordError::InvalidMessage {
            topic: topics::RECON_HEIGHT_PREVIEW.to_owned(),
            reason: format!("cannot encode the PNG: {e}"),
        })?;
        self.compressed_png(
            topics::RECON_HEIGHT_PREVIEW,
            log_time_ns,
            topics::FRAME_LEFT,
            png,
        )?;
        self.send(Entry::image_text(
            topics::RECON_HEIGHT_PREVIEW_LEGEND,
            log_time_ns,
            &legend(preview.range_um),
        )?)?;

        let cloud = ply::cloud_from_height(view.height_um, p, Some(view.intensity));
        self.point_cloud(
            topics::RECON_POINTCLOUD,
            log_time_ns,
            topics::FRAME_LEFT,
            &cloud,
        )?;

        let (mesh, stride) = ply::build_mesh_decimated(
            view.height_um,
            p,
            Some(view.intensity),
            view.mesh,
            MESH_PREVIEW_MAX_VERTICES,
        );
        let generator = concat!("sdsem ", env!("CARGO_PKG_VERSION"));
        if let Some(model) = glb::mesh_glb(&mesh, generator) {
            self.send(Entry::scene_model(
                topics::RECON_MESH,
                log_time_ns,
                topics::FRAME_LEFT,
                "mesh",
                (glb::MEDIA_TYPE, model),
                &[
                    ("unit", "µm".to_owned()),
                    (
                        "decimation",
                        if stride == 1 {
                            "every pixel".to_owned()
                        } else {
                            format!("every {stride}th pixel of each row and column")
                        },
                    ),
                    ("vertices", mesh.vertices.len().to_string()),
                    ("triangles", mesh.triangles.len().to_string()),
                    ("full mesh", "mesh.ply in the run directory".to_owned()),
                ],
            )?)?;
        }
        Ok(())
    }
}

/// The two lines over the preview: what its colours mean.
fn legend(range_um: Option<(f32, f32)>) -> Vec<String> {
    match range_um {
        Some((lo, hi)) => vec![
            format!(
                "height: dark purple {} … yellow {}",
                fmt_um(f64::from(lo)),
                fmt_um(f64::from(hi))
            ),
            "(1st–99th percentile; black: unknown)".to_owned(),
        ],
        None => vec!["no height known".to_owned()],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_legend_names_both_ends_in_micrometres() {
        let lines = legend(Some((-3.341_07, 8.027_016)));
        assert_eq!(lines[0], "height: dark purple -3.341 µm … yellow 8.027 µm");
        assert!(lines[1].contains("black: unknown"));
        assert_eq!(legend(None), ["no height known"]);
    }
}
