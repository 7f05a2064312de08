//! Topic names, frame roles and record names of the run record — DESIGN §5 (contract).

/// Every SEM frame (foxglove.RawImage mono8/mono16, or CompressedImage png);
/// the message's `frame_id` is the [`FrameRole`].
pub const SEM_FRAME: &str = "/sem/frame";
/// Per frame: tilt, stage position, pixel size, dwell, role, drift (JSON, [`super::FrameInfo`]).
pub const SEM_FRAME_INFO: &str = "/sem/frame_info";
/// Stage position after every move and every poll result that matters (JSON, [`super::StageState`]).
pub const STAGE_STATE: &str = "/stage/state";
/// Every command line sent and every reply, with timestamps and round-trip time (JSON, [`super::StageIo`]).
pub const STAGE_IO: &str = "/stage/io";
/// Height map on the left micrograph's grid, µm, NaN unknown (foxglove.RawImage 32FC1).
pub const RECON_HEIGHT: &str = "/recon/height";
/// The dense point cloud, µm (foxglove.PointCloud).
pub const RECON_POINTCLOUD: &str = "/recon/pointcloud";
/// The same figures as `report.json` (JSON).
pub const RECON_REPORT: &str = "/recon/report";
/// The tracing events of the run (foxglove.Log).
pub const LOG: &str = "/log";

/// Beyond DESIGN §5: the height map as a picture (foxglove.CompressedImage, PNG, RGB): viridis
/// over the 1st–99th percentile of the heights, unknown pixels black; `frame_id` `left`.
pub const RECON_HEIGHT_PREVIEW: &str = "/recon/height_preview";
/// The legend of [`RECON_HEIGHT_PREVIEW`]: the heights its colours span (foxglove.ImageAnnotations).
pub const RECON_HEIGHT_PREVIEW_LEGEND: &str = "/recon/height_preview/legend";
/// The mesh, decimated to at most [`super::MESH_PREVIEW_MAX_VERTICES`] vertices, as a
/// foxglove.SceneUpdate whose entity holds a glTF model (µm, frame [`FRAME_LEFT`]).
pub const RECON_MESH: &str = "/recon/mesh";
/// Where the 3D frames sit (foxglove.FrameTransforms): [`FRAME_LEFT`] in [`FRAME_SPECIMEN`].
pub const TRANSFORMS: &str = "/tf";

/// The 3D frame of the left micrograph's grid, in µm: pixel (c, r) at height h is the point
/// (c·p, −r·p, h) — x right, y up in the image, z towards the beam, as in the PLY files.
/// The point cloud, the mesh and (as its `frame_id`) the height map lie in it.
pub const FRAME_LEFT: &str = "left";
/// The parent of [`FRAME_LEFT`]: the same axes and unit, its origin at the centre of the left
/// micrograph at height 0, so a 3D view centred on the origin shows the middle of the field.
pub const FRAME_SPECIMEN: &str = "specimen";

/// All contract topics, in the order of DESIGN §5.
pub const ALL_TOPICS: [&str; 8] = [
    SEM_FRAME,
    SEM_FRAME_INFO,
    STAGE_STATE,
    STAGE_IO,
    RECON_HEIGHT,
    RECON_POINTCLOUD,
    RECON_REPORT,
    LOG,
];

/// Name of the MCAP metadata record with the job, the full effective configuration,
/// the version and the host (DESIGN §5).
pub const METADATA_RUN: &str = "sdsem.run";
/// Name of the MCAP metadata record of the instruments, written once they are connected:
/// `stage` and `sem` (their identification answers), `stage_protocol`, `sem_protocol` and,
/// where known, `stage_`/`sem_` `vendor`, `model`, `version`, `serial`.
pub const METADATA_INSTRUMENTS: &str = "sdsem.instruments";
/// Name of the MCAP metadata record of who made the frames as the frames themselves say
/// (a watched folder's vendor tags: `sem_vendor`, `sem_model`, `sem_version`, `sem_serial`),
/// written after the series when it adds to [`METADATA_INSTRUMENTS`].
pub const METADATA_INSTRUMENTS_FROM_FRAMES: &str = "sdsem.instruments.frames";
/// Name of the MCAP metadata record written last, with the run's outcome
/// (keys `status` and, on failure, `cause`). See [`super::RunOutcome`].
pub const METADATA_OUTCOME: &str = "sdsem.outcome";
/// Name of the MCAP metadata record the recorder writes at `finish()` when log
/// messages had to be dropped under backpressure (key `dropped`).
pub const METADATA_LOG_DROPS: &str = "sdsem.log_drops";

/// Attachment name of the Gwyddion height field (DESIGN §5).
pub const ATTACHMENT_HEIGHT_GSF: &str = "height.gsf";
/// Attachment name of the triangle mesh (DESIGN §5) in records written before the mesh
/// became the [`RECON_MESH`] scene entity; `mesh.ply` lies in the run directory.
pub const ATTACHMENT_MESH_PLY: &str = "mesh.ply";
/// Attachment name of the per-pixel confidence of the height map (beyond
/// DESIGN §5: 0 marks interpolated heights).
pub const ATTACHMENT_CONFIDENCE_TIFF: &str = "confidence.tif";

/// Which frame a `/sem/frame` message is: the `frame_id` of the image message and the
/// `role` of its `/sem/frame_info` — the SEM link's own [`sdsem_protocol::sem::Role`].
pub use sdsem_protocol::sem::Role as FrameRole;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles_round_trip_through_their_frame_id() {
        for role in [FrameRole::Tracking, FrameRole::Left, FrameRole::Right] {
            assert_eq!(role.as_str().parse::<FrameRole>().unwrap(), role);
            assert_eq!(
                serde_json::to_string(&role).unwrap(),
                format!("\"{}\"", role.as_str())
            );
        }
        assert!("Left".parse::<FrameRole>().is_err());
    }
}
