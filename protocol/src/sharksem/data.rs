//! The data channel: `ScData` chunks and their reassembly into one frame
//! [TS-PDF `ScScanXY`/`ScData`; TS-PY `FetchImageEx`].
//!
//! Body: `u32 frame id`, `i32 channel`, `u32 index` (pixel index of the first
//! pixel of the chunk), `i32 bpp` (8/16), then a `char[]` of pixels (16-bit
//! ones little-endian), row-major over the visible region, origin top-left.
//!
//! [`FrameAssembler`] applies TESCAN's client rules: messages of another name,
//! frame or channel are skipped; an index below the pixels received is a
//! re-send (truncate to it, then append); an index above them means a chunk
//! was lost, which fails the frame; the frame is complete after the region's
//! pixel count.

use super::body::{BodyError, BodyReader, BodyWriter};
use super::framer::Message;
use super::header::{Flags, FnName, HEADER_LEN, Header};

/// The name of image data messages.
pub const SC_DATA: &str = "ScData";

/// One `ScData` chunk.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DataChunk {
    pub frame_id: u32,
    pub channel: i32,
    /// Pixel index of the first pixel in `data`.
    pub index: u32,
    /// Bits per pixel: 8 or 16.
    pub bpp: i32,
    pub data: Vec<u8>,
}

impl DataChunk {
    /// Decodes an `ScData` body.
    ///
    /// # Errors
    /// [`BodyError`] when the body is short or its data count runs past its end.
    pub fn decode(body: &[u8]) -> Result<Self, BodyError> {
        let mut r = BodyReader::new(body);
        Ok(Self {
            frame_id: r.uint()?,
            channel: r.int()?,
            index: r.uint()?,
            bpp: r.int()?,
            data: r.bytes()?.to_vec(),
        })
    }

    /// The whole `ScData` message (id 0, flags 0, queue 0).
    #[must_use]
    pub fn encode(&self) -> Vec<u8> {
        let body = BodyWriter::new()
            .uint(self.frame_id)
            .int(self.channel)
            .uint(self.index)
            .int(self.bpp)
            .bytes(&self.data)
            .finish();
        let header = Header {
            name: FnName::new(SC_DATA).unwrap_or_else(|e| unreachable!("built-in name: {e}")),
            body_size: u32::try_from(body.len()).unwrap_or(u32::MAX),
            id: 0,
            flags: Flags::NONE,
            queue: 0,
        };
        let mut out = Vec::with_capacity(HEADER_LEN + body.len());
        out.extend_from_slice(&header.encode());
        out.extend_from_slice(&body);
        out
    }
}

/// Why a message on the data channel was passed over.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Skip {
    /// Not `ScData` (e.g. `CameraData`).
    OtherName,
    /// Another frame id (data of an earlier scan still in flight).
    OtherFrame,
    /// Another channel.
    OtherChannel,
    /// The frame is already complete.
    AfterComplete,
}

/// What one message did to the frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    Skipped(Skip),
    /// Pixels appended at the end.
    Appended,
    /// A re-send: the frame was cut back to `from` pixels and the chunk appended.
    Resent {
        from: u32,
    },
    /// The last pixel arrived.
    Complete,
}

/// Why a frame cannot be completed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AssembleError {
    /// A chunk starts beyond the pixels received: the one before it was lost.
    #[error(
        "an image data chunk was lost: {received} pixels received, the next chunk starts at pixel {index}"
    )]
    LostChunk { received: u64, index: u32 },
    /// The chunk has another bit depth than the channel was enabled with.
    #[error("image data of {got} bits per pixel where {expected} were enabled")]
    WrongDepth { expected: u8, got: i32 },
    /// More pixels than the visible region holds.
    #[error("image data runs to pixel {end}, beyond the {total} pixels of the scanned region")]
    Overflow { end: u64, total: u64 },
    /// A data byte count that is not a whole number of pixels.
    #[error("an image data chunk of {bytes} bytes is not a whole number of {bpp}-bit pixels")]
    PartialPixel { bytes: usize, bpp: u8 },
    /// An `ScData` body that does not decode.
    #[error("an image data chunk does not decode: {0}")]
    BadChunk(BodyError),
}

/// Counters of one frame's assembly, for the record.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AssemblyStats {
    /// Chunks of this frame and channel used.
    pub chunks: u32,
    /// Chunks that were re-sends.
    pub resent: u32,
    /// Messages passed over.
    pub skipped: u32,
}

/// Reassembles one frame of one channel from `ScData` chunks.
#[derive(Debug)]
pub struct FrameAssembler {
    frame_id: u32,
    channel: i32,
    bpp: u8,
    total: u64,
    data: Vec<u8>,
    stats: AssemblyStats,
}

impl FrameAssembler {
    /// Expects `pixels` pixels of `bpp` (8 or 16) bits for frame `frame_id`, channel `channel`.
    #[must_use]
    pub fn new(frame_id: u32, channel: i32, bpp: u8, pixels: u64) -> Self {
        Self {
            frame_id,
            channel,
            bpp: if bpp == 8 { 8 } else { 16 },
            total: pixels,
            data: Vec::new(),
            stats: AssemblyStats::default(),
        }
    }

    fn bytes_per_pixel(&self) -> usize {
        usize::from(self.bpp / 8)
    }

    /// Pixels received so far.
    #[must_use]
    pub fn received(&self) -> u64 {
        (self.data.len() / self.bytes_per_pixel()) as u64
    }

    /// Whether every pixel of the region arrived.
    #[must_use]
    pub fn is_complete(&self) -> bool {
        self.received() == self.total
    }

    /// The counters so far.
    #[must_use]
    pub fn stats(&self) -> AssemblyStats {
        self.stats
    }

    /// Takes one message of the data channel.
    ///
    /// # Errors
    /// [`AssembleError`]: the frame cannot be completed (the caller fails it).
    pub fn push(&mut self, message: &Message) -> Result<Progress, AssembleError> {
        if message.header.name.as_str() != SC_DATA {
            return Ok(self.skip(Skip::OtherName));
        }
        let chunk = DataChunk::decode(&message.body).map_err(AssembleError::BadChunk)?;
        self.push_chunk(&chunk)
    }

    /// Takes one decoded chunk (see [`Self::push`]).
    ///
    /// # Errors
    /// As [`Self::push`].
    pub fn push_chunk(&mut self, chunk: &DataChunk) -> Result<Progress, AssembleError> {
        if chunk.frame_id != self.frame_id {
            return Ok(self.skip(Skip::OtherFrame));
        }
        if chunk.channel != self.channel {
            return Ok(self.skip(Skip::OtherChannel));
        }
        if self.is_complete() {
            return Ok(self.skip(Skip::AfterComplete));
        }
        if chunk.bpp != i32::from(self.bpp) {
            return Err(AssembleError::WrongDepth {
                expected: self.bpp,
                got: chunk.bpp,
            });
        }
        let bpp = self.bytes_per_pixel();
        if !chunk.data.len().is_multiple_of(bpp) {
            return Err(AssembleError::PartialPixel {
                bytes: chunk.data.len(),
                bpp: self.bpp,
            });
        }
        let received = self.received();
        let index = u64::from(chunk.index);
        if index > received {
            return Err(AssembleError::LostChunk {
                received,
                index: chunk.index,
            });
        }
        let end = index + (chunk.data.len() / bpp) as u64;
        if end > self.total {
            return Err(AssembleError::Overflow {
                end,
                total: self.total,
            });
        }
        let resent = index < received;
        // index ≤ received ≤ total, which fits the buffer already allocated.
        self.data.truncate(index as usize * bpp);
        self.data.extend_from_slice(&chunk.data);
        self.stats.chunks += 1;
        if resent {
            self.stats.resent += 1;
        }
        Ok(if self.is_complete() {
            Progress::Complete
        } else if resent {
            Progress::Resent { from: chunk.index }
        } else {
            Progress::Appended
        })
    }

    fn skip(&mut self, why: Skip) -> Progress {
        self.stats.skipped += 1;
        Progress::Skipped(why)
    }

    /// The pixels received, 8-bit ones as bytes.
    #[must_use]
    pub fn into_u8(self) -> Vec<u8> {
        self.data
    }

    /// The pixels received, 16-bit little-endian ones as `u16` (8-bit ones widened).
    #[must_use]
    pub fn into_u16(self) -> Vec<u16> {
        if self.bpp == 8 {
            return self.data.into_iter().map(u16::from).collect();
        }
        self.data
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sharksem::MessageFramer;

    fn chunk(frame_id: u32, index: u32, pixels: &[u16]) -> DataChunk {
        DataChunk {
            frame_id,
            channel: 0,
            index,
            bpp: 16,
            data: pixels.iter().flat_map(|p| p.to_le_bytes()).collect(),
        }
    }

    /// Frames `messages` one byte at a time and feeds the assembler.
    fn run(asm: &mut FrameAssembler, messages: &[Vec<u8>]) -> Vec<Result<Progress, AssembleError>> {
        let mut f = MessageFramer::new();
        let mut out = Vec::new();
        for b in messages.concat() {
            f.push(&[b]);
            while let Some(m) = f.next_message() {
                out.push(asm.push(&m.unwrap()));
            }
        }
        out
    }

    #[test]
    fn chunk_body_has_the_documented_layout() {
        let bytes = chunk(7, 2, &[0x0102, 0xA0B0]).encode();
        assert_eq!(&bytes[..7], b"ScData\0");
        let body = &bytes[HEADER_LEN..];
        let words: Vec<u32> = body[..20]
            .chunks(4)
            .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(
            words,
            [7, 0, 2, 16, 4],
            "frame, channel, index, bpp, data bytes"
        );
        assert_eq!(
            &body[20..],
            &[0x02, 0x01, 0xB0, 0xA0],
            "16-bit pixels little-endian"
        );
    }

    #[test]
    fn resent_chunks_truncate_and_strangers_are_skipped() {
        let mut asm = FrameAssembler::new(5, 0, 16, 6);
        let stranger_channel = DataChunk {
            channel: 1,
            ..chunk(5, 0, &[9, 9])
        };
        let got = run(
            &mut asm,
            &[
                chunk(4, 0, &[99; 6]).encode(),
                chunk(5, 0, &[1, 2]).encode(),
                stranger_channel.encode(),
                chunk(5, 2, &[3, 4]).encode(),
                chunk(5, 2, &[30, 40]).encode(),
                chunk(5, 4, &[5, 6]).encode(),
                chunk(5, 0, &[7]).encode(),
            ],
        );
        assert_eq!(
            got,
            vec![
                Ok(Progress::Skipped(Skip::OtherFrame)),
                Ok(Progress::Appended),
                Ok(Progress::Skipped(Skip::OtherChannel)),
                Ok(Progress::Appended),
                Ok(Progress::Resent { from: 2 }),
                Ok(Progress::Complete),
                Ok(Progress::Skipped(Skip::AfterComplete)),
            ]
        );
        let stats = asm.stats();
        assert_eq!((stats.chunks, stats.resent, stats.skipped), (4, 1, 3));
        assert_eq!(asm.into_u16(), [1, 2, 30, 40, 5, 6]);
    }

    #[test]
    fn a_lost_chunk_fails_the_frame() {
        let mut asm = FrameAssembler::new(1, 0, 16, 6);
        let got = run(
            &mut asm,
            &[chunk(1, 0, &[1, 2]).encode(), chunk(1, 4, &[5, 6]).encode()],
        );
        assert_eq!(
            got[1],
            Err(AssembleError::LostChunk {
                received: 2,
                index: 4
            })
        );
        assert!(!asm.is_complete());
    }

    #[test]
    fn depth_overflow_and_broken_chunks_are_errors() {
        let mut asm = FrameAssembler::new(1, 0, 16, 2);
        let eight = DataChunk {
            bpp: 8,
            data: vec![1, 2],
            ..chunk(1, 0, &[])
        };
        assert_eq!(
            asm.push_chunk(&eight),
            Err(AssembleError::WrongDepth {
                expected: 16,
                got: 8
            })
        );
        assert!(matches!(
            asm.push_chunk(&chunk(1, 0, &[1, 2, 3])),
            Err(AssembleError::Overflow { end: 3, total: 2 })
        ));
        let odd = DataChunk {
            data: vec![1, 2, 3],
            ..chunk(1, 0, &[])
        };
        assert!(matches!(
            asm.push_chunk(&odd),
            Err(AssembleError::PartialPixel { .. })
        ));
        let mut short = chunk(1, 0, &[1]).encode();
        // Claim 400 data bytes in a body that holds 2.
        short[HEADER_LEN + 16..HEADER_LEN + 20].copy_from_slice(&400u32.to_le_bytes());
        let got = run(&mut asm, &[short]);
        assert!(matches!(got[0], Err(AssembleError::BadChunk(_))), "{got:?}");
        let other = Message {
            header: Header {
                name: FnName::new("CameraData").unwrap(),
                body_size: 0,
                id: 0,
                flags: Flags::NONE,
                queue: 0,
            },
            body: Vec::new(),
        };
        assert_eq!(asm.push(&other), Ok(Progress::Skipped(Skip::OtherName)));
    }

    #[test]
    fn eight_bit_frames_assemble_too() {
        let mut asm = FrameAssembler::new(2, 3, 8, 3);
        let c = DataChunk {
            frame_id: 2,
            channel: 3,
            index: 0,
            bpp: 8,
            data: vec![10, 20, 30],
        };
        assert_eq!(asm.push_chunk(&c), Ok(Progress::Complete));
        assert_eq!(asm.into_u16(), [10, 20, 30]);
    }
}
