//! Writers (and readers, for verification) of the result files.
//!
//! Every writer is atomic: it writes a temporary file beside the target, syncs it and
//! renames it into place ([`atomic`]), so a crash or a full disk never leaves a partial
//! file that looks valid.
//!
//! 3D coordinates (point cloud, mesh) are in µm in a right-handed frame seen from the
//! beam: x = column·p (right), y = −row·p (up in the image), z = height (towards the beam),
//! so viewers show the surface the way the micrograph shows it. See [`ply`].

pub mod atomic;
mod error;
pub mod flo;
pub mod glb;
pub mod gsf;
pub mod height_tiff;
pub mod ply;
pub mod preview;
pub mod report;

pub use error::ExportError;
pub use ply::{CloudPoint, MeshParams, cloud_from_height};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::Image;

    /// Writes every export of a synthetic dome (NaN corners) for inspection with external
    /// tools (Gwyddion, MeshLab, ImageJ/Fiji):
    /// `SDSEM_EXPORT_SAMPLES=/tmp/sdsem-exports cargo test -p sdsem --lib export::tests::write_samples -- --ignored`
    #[test]
    #[ignore = "writes sample files for external tools"]
    fn write_samples() {
        let dir = std::path::PathBuf::from(
            std::env::var("SDSEM_EXPORT_SAMPLES").unwrap_or_else(|_| "/tmp/sdsem-exports".into()),
        );
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h, p) = (160, 120, 0.05);
        let height = Image::from_fn(w, h, |x, y| {
            let (dx, dy) = (x as f32 - 80.0, y as f32 - 60.0);
            let r2 = (dx * dx + dy * dy) * 0.0025;
            if r2 > 4.0 {
                f32::NAN
            } else {
                (4.0 - r2).sqrt()
            }
        });
        let intensity = Image::from_fn(w, h, |x, y| ((x ^ y) % 32) as f32 / 31.0);
        height_tiff::write_height_tiff(&dir.join("height.tif"), &height, Some(p), None).unwrap();
        gsf::write_gsf(&dir.join("height.gsf"), &height, p, "Height").unwrap();
        let cloud = cloud_from_height(&height, p, Some(&intensity));
        ply::write_point_cloud_ply(&dir.join("pointcloud.ply"), &cloud).unwrap();
        let mesh = ply::build_mesh(&height, p, Some(&intensity), &MeshParams::default());
        ply::write_mesh_ply(&dir.join("mesh.ply"), &mesh, true).unwrap();
        report::write_json_atomic(
            &dir.join("report.json"),
            &serde_json::json!({"points": cloud.len(), "triangles": mesh.triangles.len()}),
        )
        .unwrap();
        let tags = crate::imaging::file::MicrographTags {
            pixel_size_um: Some(p),
            tilt_deg: Some(-3.0),
            ..Default::default()
        };
        crate::imaging::file::write_micrograph_tiff(
            dir.join("left.tif"),
            &intensity,
            &tags,
            crate::imaging::file::SampleDepth::Bits16,
        )
        .unwrap();
        println!(
            "wrote {}: {} points, {} triangles ({} cut)",
            dir.display(),
            cloud.len(),
            mesh.triangles.len(),
            mesh.cut_triangles
        );
    }
}
