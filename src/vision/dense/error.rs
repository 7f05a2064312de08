//! Errors of the dense stage and of SIFT flow.

/// Errors of the dense stage, each naming the cause and the remedy.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DenseError {
    #[error(
        "rectified images differ in size ({left_width}×{left_height} vs {right_width}×{right_height}); rectify both onto one canvas"
    )]
    SizeMismatch {
        left_width: usize,
        left_height: usize,
        right_width: usize,
        right_height: usize,
    },
    #[error(
        "image of {width}×{height} is too small for {levels} pyramid levels (the top level needs {min_top}×{min_top} pixels); lower `levels`"
    )]
    TooSmall {
        width: usize,
        height: usize,
        levels: usize,
        min_top: usize,
    },
    #[error("invalid dense parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error(
        "validity mask holds {len} entries for a {width}×{height} image; pass one entry per pixel"
    )]
    MaskSize {
        width: usize,
        height: usize,
        len: usize,
    },
    #[error("no valid pixel in the rectified left image; check the rectification homographies")]
    NoValidPixels,
}
