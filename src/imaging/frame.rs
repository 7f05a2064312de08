//! A frame from the SEM: its pixels and how it was taken.

use sdsem_protocol::sem::{Bits, FrameReply};
pub use sdsem_protocol::sem::{FrameMeta, Role};
use serde::{Deserialize, Serialize};

use crate::vision::Image;

/// The samples of a frame, row-major, x right, y down.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Pixels {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

impl Pixels {
    /// Number of samples.
    #[must_use]
    pub fn len(&self) -> usize {
        match self {
            Self::U8(v) => v.len(),
            Self::U16(v) => v.len(),
        }
    }

    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bits per sample.
    #[must_use]
    pub fn bits(&self) -> u32 {
        match self {
            Self::U8(_) => 8,
            Self::U16(_) => 16,
        }
    }
}

/// One scanned frame with its metadata (pixel size µm, dwell µs, stage X/Y µm
/// and tilt ° at the start of the scan, role, frame number, scan start and
/// end in ns since the Unix epoch; see [`FrameMeta`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: usize,
    pub height: usize,
    pub pixels: Pixels,
    pub meta: FrameMeta,
    /// When the client had received the whole frame, ns since the Unix epoch.
    pub received_unix_ns: u64,
    /// The file the frame was read from (watch folder); `None` for scanned frames.
    pub origin: Option<FrameFile>,
}

/// Where a frame read from a file came from and what was done to it (`/sem/frame_info`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameFile {
    /// File name in the watched folder.
    pub name: String,
    /// Whose metadata the file carries (Zeiss, FEI/Thermo Fisher, Tescan, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vendor: Option<String>,
    /// The sidecar read with it (Hitachi, JEOL).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sidecar: Option<String>,
    /// The tilt the file records, degrees (checked against the stage's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recorded_tilt_deg: Option<f64>,
    /// Width and height as stored, info bar included.
    pub stored_width: u32,
    pub stored_height: u32,
    /// Stored pixels averaged into one frame pixel per side (1: none), to bring a stored
    /// micrograph down to the tracking frame size asked for.
    pub downsampled: u32,
    /// The instrument the file's metadata names (model, software version, serial number).
    #[serde(default, skip_serializing_if = "super::SourceIdentity::is_empty")]
    pub instrument: super::SourceIdentity,
}
impl Frame {
    /// Builds a frame from a decoded `FRAME` reply.
    #[must_use]
    pub fn from_reply(reply: FrameReply, received_unix_ns: u64) -> Self {
        let pixels = match reply.bits {
            Bits::Eight => Pixels::U8(reply.data),
            Bits::Sixteen => Pixels::U16(
                reply
                    .data
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
        };
        Self {
            width: reply.width as usize,
            height: reply.height as usize,
            pixels,
            meta: reply.meta,
            received_unix_ns,
            origin: None,
        }
    }

    /// The frame as the vision core's image, intensities scaled to `[0, 1]`.
    #[must_use]
    pub fn to_image(&self) -> Image {
        // The one conversion of the vision core, so a frame read back from the
        // record gives exactly the same image (replay reproduces bit for bit).
        let image = match &self.pixels {
            Pixels::U8(v) => Image::from_u8(self.width, self.height, v),
            Pixels::U16(v) => Image::from_u16(self.width, self.height, v),
        };
        // The protocol decoder checked that the payload holds width × height samples.
        image.unwrap_or_else(|_| Image::zeros(self.width, self.height))
    }

    #[must_use]
    pub fn role(&self) -> Role {
        self.meta.role
    }

    /// Stage tilt at the start of the scan, degrees.
    #[must_use]
    pub fn tilt_deg(&self) -> f64 {
        self.meta.tilt_deg
    }

    /// Pixel size, µm.
    #[must_use]
    pub fn pixel_size_um(&self) -> f64 {
        self.meta.pixel_size_um
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> FrameMeta {
        FrameMeta {
            frame: 1,
            role: Role::Tracking,
            pixel_size_um: 0.4,
            dwell_us: 1.0,
            stage_x_um: 0.0,
            stage_y_um: 0.0,
            tilt_deg: 2.0,
            tilt_axis_deg: 0.0,
            scan_rotation_deg: 0.0,
            scan_start_unix_ns: 0,
            scan_end_unix_ns: 0,
        }
    }

    #[test]
    fn sixteen_bit_frame_becomes_a_unit_range_image() {
        let f = Frame::from_reply(FrameReply::from_u16(2, 1, meta(), &[0, 65535]), 5);
        assert_eq!(f.pixels, Pixels::U16(vec![0, 65535]));
        let img = f.to_image();
        assert_eq!(img.dimensions(), (2, 1));
        assert_eq!(img.data(), &[0.0, 1.0]);
        assert_eq!(f.tilt_deg(), 2.0);
    }

    #[test]
    fn eight_bit_frame_becomes_a_unit_range_image() {
        let f = Frame::from_reply(FrameReply::from_u8(1, 2, meta(), vec![255, 0]), 5);
        assert_eq!(f.pixels.bits(), 8);
        assert_eq!(f.to_image().data(), &[1.0, 0.0]);
    }
}
