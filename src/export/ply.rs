//! `pointcloud.ply` and `mesh.ply`: binary little-endian PLY 1.0.
//!
//! Coordinates are µm in a right-handed frame seen from the beam: a pixel at column c,
//! row r of the left micrograph with height h becomes (x, y, z) = (c·p, −r·p, h), p the
//! pixel size. (Image rows go down; flipping y keeps the frame right-handed, so viewers
//! show the surface unmirrored with z towards the beam.)
//!
//! The mesh joins valid neighbouring pixels: each 2×2 block gives up to two triangles,
//! and a triangle is left out when any of its edges crosses a depth discontinuity — a
//! height step larger than [`MeshParams::max_step_px`] pixel sizes per pixel of edge
//! length, i.e. a surface steeper than atan(max_step_px) (79° by default), which SEM
//! stereo cannot observe and which therefore marks an occlusion edge, not a wall.

use std::io::Write;
use std::path::Path;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ExportError;
use super::atomic::{EarlyWriteback, Target};
use crate::vision::Image;

/// One point of the dense cloud: position in µm (see the module docs) and intensity.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct CloudPoint {
    pub x: f32,
    pub y: f32,
    pub z: f32,
    /// Micrograph intensity at the point, `[0, 1]`.
    pub intensity: f32,
}

/// Parameters of the triangle mesh.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeshParams {
    /// Largest height step between mesh neighbours, in pixel sizes per pixel of distance
    /// (a slope of `max_step_px`). Default 5 (≈ 79°): steeper edges are treated as depth
    /// discontinuities and not triangulated. Lower it to cut more aggressively at
    /// occlusions; raise it to close steep walls.
    pub max_step_px: f64,
}

impl Default for MeshParams {
    fn default() -> Self {
        Self { max_step_px: 5.0 }
    }
}

/// A mesh over the pixel grid.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    pub vertices: Vec<CloudPoint>,
    /// Vertex indices, counter-clockwise seen from +z (normals towards the beam).
    pub triangles: Vec<[u32; 3]>,
    /// Triangles left out because an edge crossed a depth discontinuity.
    pub cut_triangles: usize,
}

fn point(c: usize, r: usize, h: f32, p: f64, intensity: Option<&Image>) -> CloudPoint {
    CloudPoint {
        x: (c as f64 * p) as f32,
        y: (-(r as f64) * p) as f32,
        z: h,
        intensity: intensity.map_or(0.0, |i| i.get(c, r)),
    }
}

/// The dense point cloud of a height map: one point per finite height.
///
/// # Panics
/// When `intensity` is given with other dimensions than `height_um`.
#[must_use]
pub fn cloud_from_height(
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
) -> Vec<CloudPoint> {
    if let Some(i) = intensity {
        assert_eq!(i.dimensions(), height_um.dimensions(), "intensity grid");
    }
    let mut points = Vec::new();
    for r in 0..height_um.height() {
        for (c, &h) in height_um.row(r).iter().enumerate() {
            if h.is_finite() {
                points.push(point(c, r, h, pixel_size_um, intensity));
            }
        }
    }
    points
}

/// Triangulates the valid pixels of a height map (see the module docs).
///
/// # Panics
/// When `intensity` is given with other dimensions than `height_um`.
#[must_use]
pub fn build_mesh(
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
    params: &MeshParams,
) -> Mesh {
    if let Some(i) = intensity {
        assert_eq!(i.dimensions(), height_um.dimensions(), "intensity grid");
    }
    let (w, h) = height_um.dimensions();
    let mut index = vec![u32::MAX; w * h];
    let mut mesh = Mesh::default();
    for r in 0..h {
        for c in 0..w {
            let z = height_um.get(c, r);
            if z.is_finite() {
                // More than 4 billion vertices would not fit a PLY int index anyway.
                index[r * w + c] = mesh.vertices.len() as u32;
                mesh.vertices.push(point(c, r, z, pixel_size_um, intensity));
            }
        }
    }
    let max_step = params.max_step_px * pixel_size_um;
    let continuous = |a: (usize, usize), b: (usize, usize)| {
        let dist = if a.0 != b.0 && a.1 != b.1 {
            std::f64::consts::SQRT_2
        } else {
            1.0
        };
        let dz = f64::from(height_um.get(a.0, a.1) - height_um.get(b.0, b.1)).abs();
        dz <= max_step * dist
    };
    for r in 0..h.saturating_sub(1) {
        for c in 0..w.saturating_sub(1) {
            // a b
            // e d   (image rows go down; y = −r·p)
            let (a, b, d, e) = ((c, r), (c + 1, r), (c + 1, r + 1), (c, r + 1));
            let id = |(x, y): (usize, usize)| index[y * w + x];
            if [a, b, d, e].iter().any(|&q| id(q) == u32::MAX) {
                continue;
            }
            for tri in [[a, e, d], [a, d, b]] {
                if continuous(tri[0], tri[1])
                    && continuous(tri[1], tri[2])
                    && continuous(tri[2], tri[0])
                {
                    mesh.triangles.push([id(tri[0]), id(tri[1]), id(tri[2])]);
                } else {
                    mesh.cut_triangles += 1;
                }
            }
        }
    }
    mesh
}

/// A mesh of at most `max_vertices` vertices, for viewers of a whole run (the record's
/// `/recon/mesh`): [`build_mesh`] of every `stride`-th pixel of each row and column, the
/// smallest stride that fits, with the same slope rule and in the same coordinates.
/// Returns the mesh and the stride.
///
/// # Panics
/// When `intensity` is given with other dimensions than `height_um`.
#[must_use]
pub fn build_mesh_decimated(
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
    params: &MeshParams,
    max_vertices: usize,
) -> (Mesh, usize) {
    let (w, h) = height_um.dimensions();
    let stride = (1..)
        .find(|s| w.div_ceil(*s) * h.div_ceil(*s) <= max_vertices.max(1))
        .unwrap_or(1);
    if stride == 1 {
        return (build_mesh(height_um, pixel_size_um, intensity, params), 1);
    }
    let sample = |img: &Image| {
        Image::from_fn(w.div_ceil(stride), h.div_ceil(stride), |x, y| {
            img.get(x * stride, y * stride)
        })
    };
    let intensity = intensity.map(sample);
    let mesh = build_mesh(
        &sample(height_um),
        pixel_size_um * stride as f64,
        intensity.as_ref(),
        params,
    );
    (mesh, stride)
}

/// Records per block of [`write_records`]: 1–2 MB of output at a time.
const RECORDS_PER_BLOCK: usize = 1 << 16;

/// Writes `items` as fixed-size binary records of `size` bytes, `encode`
/// filling one record: a block of records is encoded in parallel into a
/// reused buffer, then written in one call (a `write_all` per 4-byte field
/// made the 50 MB mesh of a 1280×960 map take 170 ms). The bytes are those
/// of encoding the items one after the other.
fn write_records<T: Sync>(
    w: &mut impl Write,
    items: &[T],
    size: usize,
    encode: impl Fn(&T, &mut [u8]) + Sync,
) -> std::io::Result<()> {
    let mut buf = Vec::new();
    for block in items.chunks(RECORDS_PER_BLOCK) {
        buf.clear();
        buf.resize(block.len() * size, 0);
        buf.par_chunks_mut(size)
            .zip(block)
            .for_each(|(out, item)| encode(item, out));
        w.write_all(&buf)?;
    }
    Ok(())
}

/// The bytes of one vertex: `x y z [intensity]`, float32 little-endian.
fn encode_vertex(p: &CloudPoint, with_intensity: bool, out: &mut [u8]) {
    let fields: &[f32] = if with_intensity {
        &[p.x, p.y, p.z, p.intensity]
    } else {
        &[p.x, p.y, p.z]
    };
    for (o, v) in out.chunks_exact_mut(4).zip(fields) {
        o.copy_from_slice(&v.to_le_bytes());
    }
}

/// The bytes of one face: the count 3 as `uchar`, then three `int` indices.
fn encode_face(t: &[u32; 3], out: &mut [u8]) {
    out[0] = 3;
    for (o, &i) in out[1..].chunks_exact_mut(4).zip(t) {
        // Indices come from a Vec index and PLY stores int32.
        #[allow(clippy::cast_possible_wrap)]
        o.copy_from_slice(&(i as i32).to_le_bytes());
    }
}

/// Writes `pointcloud.ply` atomically: `x y z intensity`, float32, µm.
///
/// # Errors
/// [`ExportError::Write`] on I/O failure.
pub fn write_point_cloud_ply<'a>(
    target: impl Into<Target<'a>>,
    points: &[CloudPoint],
) -> Result<(), ExportError> {
    target.into().write(|w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment sdsem dense point cloud, units: micrometre\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property float intensity\nend_header\n",
            points.len()
        )?;
        write_records(w, points, 16, |p, out| encode_vertex(p, true, out))?;
        Ok(())
    })
}

/// Writes a mesh as PLY atomically: vertices `x y z [intensity]` float32 (µm), faces as
/// `uchar`-counted `int` index lists.
///
/// # Errors
/// [`ExportError::Write`] on I/O failure.
pub fn write_mesh_ply<'a>(
    target: impl Into<Target<'a>>,
    mesh: &Mesh,
    with_intensity: bool,
) -> Result<(), ExportError> {
    target.into().write(|w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment sdsem surface mesh, units: micrometre\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n{}\
             element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            mesh.vertices.len(),
            if with_intensity {
                "property float intensity\n"
            } else {
                ""
            },
            mesh.triangles.len()
        )?;
        let vertex_size = if with_intensity { 16 } else { 12 };
        write_records(w, &mesh.vertices, vertex_size, |p, out| {
            encode_vertex(p, with_intensity, out);
        })?;
        write_records(w, &mesh.triangles, 13, encode_face)
    })
}

/// Rows of the height map encoded at a time by the streaming writers: a few MB of output.
const ROWS_PER_BLOCK: usize = 64;

/// What [`write_mesh_from_height`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MeshCounts {
    pub vertices: usize,
    pub triangles: usize,
    /// Triangles left out because an edge crossed a depth discontinuity.
    pub cut_triangles: usize,
}

/// The cells of the row pair `r, r + 1` of a height map as [`build_mesh`] triangulates them: each
/// kept triangle as `(corner, corner, corner)` pixel positions, and the count of cut ones.
fn row_triangles(
    height_um: &Image,
    r: usize,
    max_step: f64,
    mut emit: impl FnMut([(usize, usize); 3]),
) -> usize {
    let w = height_um.width();
    let continuous = |a: (usize, usize), b: (usize, usize)| {
        let dist = if a.0 != b.0 && a.1 != b.1 {
            std::f64::consts::SQRT_2
        } else {
            1.0
        };
        let dz = f64::from(height_um.get(a.0, a.1) - height_um.get(b.0, b.1)).abs();
        dz <= max_step * dist
    };
    let mut cut = 0;
    for c in 0..w.saturating_sub(1) {
        let (a, b, d, e) = ((c, r), (c + 1, r), (c + 1, r + 1), (c, r + 1));
        if [a, b, d, e]
            .iter()
            .any(|&(x, y)| !height_um.get(x, y).is_finite())
        {
            continue;
        }
        for tri in [[a, e, d], [a, d, b]] {
            if continuous(tri[0], tri[1])
                && continuous(tri[1], tri[2])
                && continuous(tri[2], tri[0])
            {
                emit(tri);
            } else {
                cut += 1;
            }
        }
    }
    cut
}

/// Writes the byte blocks `encode` makes of `blocks`, in order, encoding the next block while
/// the previous one is written: the copy into the page cache takes one core, the encoding the
/// others. The bytes are those of encoding and writing the blocks one after the other.
fn write_pipelined<B: Send>(
    w: &mut (impl Write + Send),
    blocks: impl Iterator<Item = B>,
    encode: impl Fn(B) -> Vec<Vec<u8>> + Sync,
) -> std::io::Result<()> {
    let write = |w: &mut (dyn Write + Send), encoded: &[Vec<u8>]| {
        encoded.iter().try_for_each(|bytes| w.write_all(bytes))
    };
    let mut pending: Vec<Vec<u8>> = Vec::new();
    for block in blocks {
        let (written, next) = rayon::join(|| write(&mut *w, &pending), || encode(block));
        written?;
        pending = next;
    }
    write(w, &pending)
}

/// Writes the vertices of `height_um`'s finite pixels, row-major, a block of rows at a time.
fn write_height_vertices(
    w: &mut (impl Write + Send),
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
    with_intensity: bool,
) -> std::io::Result<()> {
    let size = if with_intensity { 16 } else { 12 };
    let rows: Vec<usize> = (0..height_um.height()).collect();
    write_pipelined(w, rows.chunks(ROWS_PER_BLOCK), |block| {
        block
            .par_iter()
            .map(|&r| {
                let mut out = Vec::new();
                for (c, &h) in height_um.row(r).iter().enumerate() {
                    if h.is_finite() {
                        let at = out.len();
                        out.resize(at + size, 0);
                        let p = point(c, r, h, pixel_size_um, intensity);
                        encode_vertex(&p, with_intensity, &mut out[at..]);
                    }
                }
                out
            })
            .collect()
    })
}

/// Writes `pointcloud.ply` atomically from a height map, a block of rows at a time: the bytes
/// of [`write_point_cloud_ply`] of [`cloud_from_height`] without holding the cloud. The number of
/// points written.
///
/// # Errors
/// [`ExportError::Write`] on I/O failure.
///
/// # Panics
/// When `intensity` is given with other dimensions than `height_um`.
pub fn write_point_cloud_from_height<'a>(
    target: impl Into<Target<'a>>,
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
) -> Result<usize, ExportError> {
    if let Some(i) = intensity {
        assert_eq!(i.dimensions(), height_um.dimensions(), "intensity grid");
    }
    let n = height_um
        .data()
        .par_iter()
        .filter(|h| h.is_finite())
        .count();
    target.into().write(|w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment sdsem dense point cloud, units: micrometre\n\
             element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n\
             property float intensity\nend_header\n",
        )?;
        write_height_vertices(
            &mut EarlyWriteback::new(w),
            height_um,
            pixel_size_um,
            intensity,
            true,
        )
    })?;
    Ok(n)
}

/// Writes a mesh as PLY atomically straight from a height map, a block of rows at a time: the
/// bytes of [`write_mesh_ply`] of [`build_mesh`] without holding the mesh (on a 50-megapixel map
/// that is GiBs).
///
/// # Errors
/// [`ExportError::Write`] on I/O failure.
///
/// # Panics
/// When `intensity` is given with other dimensions than `height_um`.
pub fn write_mesh_from_height<'a>(
    target: impl Into<Target<'a>>,
    height_um: &Image,
    pixel_size_um: f64,
    intensity: Option<&Image>,
    params: &MeshParams,
    with_intensity: bool,
) -> Result<MeshCounts, ExportError> {
    if let Some(i) = intensity {
        assert_eq!(i.dimensions(), height_um.dimensions(), "intensity grid");
    }
    let h = height_um.height();
    let max_step = params.max_step_px * pixel_size_um;
    // First pass: the index of each row's first vertex and the triangles of each row pair.
    let per_row: Vec<(usize, usize, usize)> = (0..h)
        .into_par_iter()
        .map(|r| {
            let vertices = height_um.row(r).iter().filter(|v| v.is_finite()).count();
            let (mut kept, mut cut) = (0, 0);
            if r + 1 < h {
                cut = row_triangles(height_um, r, max_step, |_| kept += 1);
            }
            (vertices, kept, cut)
        })
        .collect();
    let mut first = Vec::with_capacity(h + 1);
    first.push(0usize);
    for &(v, _, _) in &per_row {
        first.push(first.last().copied().unwrap_or(0) + v);
    }
    let counts = MeshCounts {
        vertices: first[h],
        triangles: per_row.iter().map(|r| r.1).sum(),
        cut_triangles: per_row.iter().map(|r| r.2).sum(),
    };
    target.into().write(|out| {
        write!(
            out,
            "ply\nformat binary_little_endian 1.0\ncomment sdsem surface mesh, units: micrometre\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n{}\
             element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            counts.vertices,
            if with_intensity {
                "property float intensity\n"
            } else {
                ""
            },
            counts.triangles
        )?;
        let out = &mut EarlyWriteback::new(out);
        write_height_vertices(out, height_um, pixel_size_um, intensity, with_intensity)?;
        // A vertex's index: its row's first index and the finite pixels before it in the row.
        let row_index = |r: usize| -> Vec<u32> {
            let mut next = first[r];
            height_um
                .row(r)
                .iter()
                .map(|v| {
                    // More than 4 billion vertices would not fit a PLY int index anyway.
                    let i = next as u32;
                    next += usize::from(v.is_finite());
                    i
                })
                .collect()
        };
        let rows: Vec<usize> = (0..h.saturating_sub(1)).collect();
        write_pipelined(out, rows.chunks(ROWS_PER_BLOCK), |block| {
            block
                .par_iter()
                .map(|&r| {
                    let (top, bottom) = (row_index(r), row_index(r + 1));
                    let id = |(x, y): (usize, usize)| if y == r { top[x] } else { bottom[x] };
                    let mut bytes = Vec::with_capacity(13 * per_row[r].1);
                    row_triangles(height_um, r, max_step, |tri| {
                        let mut face = [0u8; 13];
                        encode_face(&[id(tri[0]), id(tri[1]), id(tri[2])], &mut face);
                        bytes.extend_from_slice(&face);
                    });
                    bytes
                })
                .collect()
        })
    })?;
    Ok(counts)
}

/// A binary little-endian PLY file read back (float vertex properties, triangle faces) —
/// enough to verify what this module writes.
#[derive(Debug, Clone, PartialEq)]
pub struct PlyData {
    /// Names of the vertex properties, in order.
    pub vertex_properties: Vec<String>,
    /// Vertex property values, row-major (`vertex_properties.len()` per vertex).
    pub vertex_data: Vec<f32>,
    pub faces: Vec<[u32; 3]>,
}

impl PlyData {
    #[must_use]
    pub fn vertex_count(&self) -> usize {
        self.vertex_data.len() / self.vertex_properties.len().max(1)
    }

    /// The vertices as points (`intensity` 0 when the file has none); `None` unless the
    /// first properties are `x y z`.
    #[must_use]
    pub fn points(&self) -> Option<Vec<CloudPoint>> {
        let n = self.vertex_properties.len();
        if n < 3 || self.vertex_properties[..3] != ["x", "y", "z"] {
            return None;
        }
        let has_i = self
            .vertex_properties
            .get(3)
            .is_some_and(|p| p == "intensity");
        Some(
            self.vertex_data
                .chunks_exact(n)
                .map(|v| CloudPoint {
                    x: v[0],
                    y: v[1],
                    z: v[2],
                    intensity: if has_i { v[3] } else { 0.0 },
                })
                .collect(),
        )
    }
}

/// Reads a PLY file as written by this module, checking the header and the exact size.
///
/// # Errors
/// [`ExportError::Read`] on I/O failure, [`ExportError::Format`] for anything else.
pub fn read_ply(path: &Path) -> Result<PlyData, ExportError> {
    let bytes = std::fs::read(path).map_err(|source| ExportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_ply(&bytes).map_err(|reason| ExportError::Format {
        path: path.to_path_buf(),
        format: "binary PLY",
        reason,
    })
}

fn parse_ply(bytes: &[u8]) -> Result<PlyData, String> {
    const END: &[u8] = b"end_header\n";
    let end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .ok_or("no end_header line")?
        + END.len();
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "header is not text")?;
    let mut lines = header.lines();
    if lines.next() != Some("ply") {
        return Err("does not start with \"ply\"".to_owned());
    }
    let (mut vertices, mut faces) = (0usize, 0usize);
    let mut props = Vec::new();
    let mut element = "";
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", "binary_little_endian", "1.0"] | ["comment", ..] | ["end_header"] => {}
            ["format", other, ..] => return Err(format!("unsupported format {other}")),
            ["element", "vertex", n] => {
                element = "vertex";
                vertices = n.parse().map_err(|_| format!("bad vertex count {n}"))?;
            }
            ["element", "face", n] => {
                element = "face";
                faces = n.parse().map_err(|_| format!("bad face count {n}"))?;
            }
            ["property", "float", name] if element == "vertex" => props.push((*name).to_owned()),
            ["property", "list", "uchar", "int", "vertex_indices"] if element == "face" => {}
            _ => return Err(format!("unsupported header line {line:?}")),
        }
    }
    let vertex_bytes = vertices * props.len() * 4;
    let expected = end + vertex_bytes + faces * 13;
    if bytes.len() != expected {
        return Err(format!(
            "size is {} bytes, header says {expected}",
            bytes.len()
        ));
    }
    let f32_at = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let vertex_data = bytes[end..end + vertex_bytes]
        .chunks_exact(4)
        .map(f32_at)
        .collect();
    let mut face_list = Vec::with_capacity(faces);
    for f in bytes[end + vertex_bytes..].chunks_exact(13) {
        if f[0] != 3 {
            return Err(format!("face with {} vertices, expected 3", f[0]));
        }
        let mut tri = [0u32; 3];
        for (k, idx) in tri.iter_mut().enumerate() {
            let b = &f[1 + 4 * k..5 + 4 * k];
            let i = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            *idx = u32::try_from(i)
                .ok()
                .filter(|&i| (i as usize) < vertices)
                .ok_or_else(|| format!("face index {i} outside 0..{vertices}"))?;
        }
        face_list.push(tri);
    }
    Ok(PlyData {
        vertex_properties: props,
        vertex_data,
        faces: face_list,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The streaming writers give the very bytes of building the cloud and mesh first.
    #[test]
    fn streamed_cloud_and_mesh_are_the_bytes_of_the_built_ones() {
        // More rows than one block: the blocks are written while the next is encoded.
        let (w, h) = (37, 2 * ROWS_PER_BLOCK + 29);
        let height = Image::from_fn(w, h, |x, y| {
            if (x * 7 + y * 3) % 11 == 0 {
                f32::NAN
            } else if x > 20 {
                2.0 + 0.01 * y as f32
            } else {
                0.05 * (x as f32 - y as f32)
            }
        });
        let intensity = Image::from_fn(w, h, |x, y| ((x + 2 * y) % 9) as f32 / 9.0);
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let params = MeshParams { max_step_px: 1.0 };
        let (p, i) = (0.25, Some(&intensity));
        let cloud = cloud_from_height(&height, p, i);
        write_point_cloud_ply(&d.join("a.ply"), &cloud).unwrap();
        let n = write_point_cloud_from_height(&d.join("b.ply"), &height, p, i).unwrap();
        assert_eq!(n, cloud.len());
        let bytes = |name: &str| std::fs::read(d.join(name)).unwrap();
        assert_eq!(bytes("a.ply"), bytes("b.ply"));
        let mesh = build_mesh(&height, p, i, &params);
        assert!(mesh.cut_triangles > 0 && !mesh.triangles.is_empty());
        for with_intensity in [true, false] {
            write_mesh_ply(&d.join("c.ply"), &mesh, with_intensity).unwrap();
            let counts =
                write_mesh_from_height(&d.join("e.ply"), &height, p, i, &params, with_intensity)
                    .unwrap();
            assert_eq!(
                (counts.vertices, counts.triangles, counts.cut_triangles),
                (
                    mesh.vertices.len(),
                    mesh.triangles.len(),
                    mesh.cut_triangles
                )
            );
            assert_eq!(bytes("c.ply"), bytes("e.ply"), "intensity {with_intensity}");
        }
    }

    /// The decimated mesh keeps the bound, the coordinates of the full one and its cuts.
    #[test]
    fn decimated_mesh_keeps_the_bound_and_the_coordinates() {
        let height = Image::from_fn(
            100,
            60,
            |x, y| {
                if x >= 50 { 40.0 } else { (x + y) as f32 * 0.01 }
            },
        );
        let (full, stride) = build_mesh_decimated(&height, 0.1, None, &MeshParams::default(), 6000);
        assert_eq!(stride, 1);
        assert_eq!(full, build_mesh(&height, 0.1, None, &MeshParams::default()));
        let (small, stride) =
            build_mesh_decimated(&height, 0.1, None, &MeshParams::default(), 1000);
        assert_eq!(stride, 3, "34 × 20 = 680 ≤ 1000 < 50 × 30");
        assert_eq!(small.vertices.len(), 34 * 20);
        // Vertex (column 2, row 1) of the small mesh is pixel (6, 3) of the map.
        let v = small.vertices[34 + 2];
        assert!(
            (v.x - 0.6).abs() < 1e-6 && (v.y + 0.3).abs() < 1e-6,
            "{v:?}"
        );
        assert_eq!(v.z, height.get(6, 3));
        // The 40 µm wall is still cut, not bridged.
        assert!(small.cut_triangles > 0);
        assert!(small.triangles.iter().all(|t| {
            let z: Vec<f32> = t.iter().map(|&i| small.vertices[i as usize].z).collect();
            z.iter().all(|&h| h == 40.0) || z.iter().all(|&h| h < 40.0)
        }));
    }

    #[test]
    fn cloud_maps_pixels_to_right_handed_micrometres() {
        let mut h = Image::from_fn(3, 2, |x, y| (x + 10 * y) as f32);
        h.set(1, 0, f32::NAN);
        let intensity = Image::filled(3, 2, 0.5);
        let cloud = cloud_from_height(&h, 0.5, Some(&intensity));
        assert_eq!(cloud.len(), 5, "NaN pixel must be skipped");
        let last = cloud[4];
        assert_eq!(
            (last.x, last.y, last.z, last.intensity),
            (1.0, -0.5, 12.0, 0.5)
        );
    }

    #[test]
    fn mesh_has_two_triangles_per_valid_block_facing_the_beam() {
        let h = Image::filled(3, 3, 1.0);
        let mesh = build_mesh(&h, 1.0, None, &MeshParams::default());
        assert_eq!(mesh.vertices.len(), 9);
        assert_eq!(mesh.triangles.len(), 8);
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            let nz = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
            assert!(nz > 0.0, "triangle {t:?} faces away from the beam");
        }
    }

    #[test]
    fn mesh_skips_blocks_with_unknown_pixels() {
        let mut h = Image::filled(3, 3, 1.0);
        h.set(1, 1, f32::NAN);
        // Every 2×2 block contains the centre pixel.
        assert!(
            build_mesh(&h, 1.0, None, &MeshParams::default())
                .triangles
                .is_empty()
        );
    }

    #[test]
    fn mesh_cuts_depth_discontinuities_but_keeps_steep_slopes() {
        // Left half at 0, right half 20 pixel sizes higher: a cliff.
        let cliff = Image::from_fn(4, 2, |x, _| if x < 2 { 0.0 } else { 20.0 });
        let mesh = build_mesh(&cliff, 1.0, None, &MeshParams::default());
        assert_eq!(
            mesh.triangles.len(),
            4,
            "the block straddling the cliff is cut"
        );
        assert_eq!(mesh.cut_triangles, 2);
        // A continuous 70° slope (step tan 70° ≈ 2.7 px per px) stays closed.
        let slope = Image::from_fn(4, 2, |x, _| x as f32 * 2.7);
        let mesh = build_mesh(&slope, 1.0, None, &MeshParams::default());
        assert_eq!((mesh.triangles.len(), mesh.cut_triangles), (6, 0));
    }

    #[test]
    fn ply_files_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let h = Image::from_fn(3, 2, |x, y| (x * y) as f32 * 0.1);
        let intensity = Image::from_fn(3, 2, |x, _| x as f32 / 2.0);
        let cloud = cloud_from_height(&h, 0.25, Some(&intensity));
        let path = dir.path().join("pointcloud.ply");
        write_point_cloud_ply(&path, &cloud).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back.vertex_properties, ["x", "y", "z", "intensity"]);
        assert_eq!(back.points().unwrap(), cloud);
        assert!(back.faces.is_empty());

        let mesh = build_mesh(&h, 0.25, Some(&intensity), &MeshParams::default());
        let path = dir.path().join("mesh.ply");
        write_mesh_ply(&path, &mesh, true).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back.vertex_count(), 6);
        assert_eq!(back.faces, mesh.triangles);
        assert_eq!(back.points().unwrap(), mesh.vertices);

        write_mesh_ply(&path, &mesh, false).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back.vertex_properties, ["x", "y", "z"]);
        assert_eq!(back.faces.len(), 4);
    }

    #[test]
    fn block_encoding_gives_the_bytes_of_field_by_field_writes() {
        // More than two blocks, the last one partial.
        let n = 2 * RECORDS_PER_BLOCK + 5;
        let points: Vec<CloudPoint> = (0..n)
            .map(|i| CloudPoint {
                x: i as f32,
                y: -(i as f32) * 0.5,
                z: (i % 7) as f32 - 3.25,
                intensity: (i % 11) as f32 / 10.0,
            })
            .collect();
        let faces: Vec<[u32; 3]> = (0..n as u32)
            .map(|i| [i, i ^ 1, i.wrapping_mul(7)])
            .collect();
        let mut want = Vec::new();
        for p in &points {
            for v in [p.x, p.y, p.z, p.intensity] {
                want.extend_from_slice(&v.to_le_bytes());
            }
        }
        for t in &faces {
            want.push(3);
            for &i in t {
                want.extend_from_slice(&(i as i32).to_le_bytes());
            }
        }
        let mut got = Vec::new();
        write_records(&mut got, &points, 16, |p, out| encode_vertex(p, true, out)).unwrap();
        write_records(&mut got, &faces, 13, encode_face).unwrap();
        assert_eq!(got, want);
        // Without intensity: x y z only.
        let mut got = Vec::new();
        write_records(&mut got, &points[..2], 12, |p, out| {
            encode_vertex(p, false, out)
        })
        .unwrap();
        assert_eq!(got[12..16], 1f32.to_le_bytes());
        assert_eq!(got.len(), 24);
    }

    #[test]
    fn reader_rejects_truncated_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.ply");
        write_point_cloud_ply(&path, &[CloudPoint::default(); 3]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
        assert!(read_ply(&path).unwrap_err().to_string().contains("size"));
    }
}
