//! A triangle mesh as binary glTF 2.0 (`.glb`, Khronos glTF 2.0 specification §4.4): the
//! model Foxglove's 3D panel shows (foxglove.ModelPrimitive, media type [`MEDIA_TYPE`]).
//!
//! One mesh, one primitive: float32 positions, the micrograph intensity as a grey vertex
//! colour (`COLOR_0`), 16-bit indices when the vertices allow it, 32-bit otherwise, and a
//! rough, non-metallic, double-sided material. No normals: viewers shade it flat (§3.7.2.1).
//!
//! Axes: glTF is y-up. A mesh point (x, y, z) of the export frame (x right, y up in the image,
//! z towards the beam; see [`super::ply`]) is written as (x, z, −y), so the height is the
//! glTF "up" and a viewer that turns y-up into its own z-up (Foxglove) shows the point at
//! (x, y, z) again. The unit is the mesh's own (µm), not glTF's metre.

use serde_json::json;

use super::ply::Mesh;

/// The IANA media type of a `.glb` file.
pub const MEDIA_TYPE: &str = "model/gltf-binary";

const MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A; // "JSON"
const CHUNK_BIN: u32 = 0x004E_4942; // "BIN\0"
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const FLOAT: u32 = 5126;
const UNSIGNED_BYTE: u32 = 5121;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_INT: u32 = 5125;

/// `mesh` as a `.glb` file's bytes; `None` for a mesh without triangles (glTF accessors
/// hold at least one element).
#[must_use]
pub fn mesh_glb(mesh: &Mesh, generator: &str) -> Option<Vec<u8>> {
    if mesh.triangles.is_empty() || mesh.vertices.is_empty() {
        return None;
    }
    let n = mesh.vertices.len();
    let mut positions = Vec::with_capacity(n * 12);
    let mut colours = Vec::with_capacity(n * 4);
    let (mut min, mut max) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in &mesh.vertices {
        let p = [v.x, v.z, -v.y];
        for i in 0..3 {
            min[i] = min[i].min(p[i]);
            max[i] = max[i].max(p[i]);
            positions.extend_from_slice(&p[i].to_le_bytes());
        }
        // Intensity in [0, 1] → 0..=255.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let grey = (v.intensity.clamp(0.0, 1.0) * 255.0).round() as u8;
        colours.extend_from_slice(&[grey, grey, grey, 255]);
    }
    // An index of u16::MAX is reserved (primitive restart), so 16 bits serve up to 65 535 vertices.
    let short = n < usize::from(u16::MAX);
    let mut indices = Vec::with_capacity(mesh.triangles.len() * if short { 6 } else { 12 });
    for &i in mesh.triangles.iter().flatten() {
        if short {
            // i < n < u16::MAX.
            #[allow(clippy::cast_possible_truncation)]
            indices.extend_from_slice(&(i as u16).to_le_bytes());
        } else {
            indices.extend_from_slice(&i.to_le_bytes());
        }
    }
    pad(&mut indices, 0);
    // Positions (12 B per vertex) and colours (4 B) keep 4-byte alignment; indices go last.
    let views = [
        (0, positions.len(), ARRAY_BUFFER),
        (positions.len(), colours.len(), ARRAY_BUFFER),
        (
            positions.len() + colours.len(),
            indices.len(),
            ELEMENT_ARRAY_BUFFER,
        ),
    ];
    let mut bin = positions;
    bin.extend_from_slice(&colours);
    bin.extend_from_slice(&indices);
    let gltf = json!({
        "asset": {"version": "2.0", "generator": generator},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "sdsem height map"}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "COLOR_0": 1},
            "indices": 2,
            "material": 0,
            "mode": 4,
        }]}],
        "materials": [{
            "pbrMetallicRoughness": {
                "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            "doubleSided": true,
        }],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views.iter().map(|&(offset, len, target)| json!({
            "buffer": 0, "byteOffset": offset, "byteLength": len, "target": target,
        })).collect::<Vec<_>>(),
        "accessors": [
            {"bufferView": 0, "componentType": FLOAT, "count": n, "type": "VEC3",
             "min": min, "max": max},
            {"bufferView": 1, "componentType": UNSIGNED_BYTE, "normalized": true, "count": n,
             "type": "VEC4"},
            {"bufferView": 2, "componentType": if short { UNSIGNED_SHORT } else { UNSIGNED_INT },
             "count": mesh.triangles.len() * 3, "type": "SCALAR"},
        ],
    });
    let mut json_chunk = gltf.to_string().into_bytes();
    pad(&mut json_chunk, b' ');
    pad(&mut bin, 0);
    let total = 12 + 8 + json_chunk.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&2u32.to_le_bytes());
    // A GLB's length is a u32 by the specification; the decimated meshes are a few MB.
    out.extend_from_slice(&u32::try_from(total).ok()?.to_le_bytes());
    for (chunk, kind) in [(&json_chunk, CHUNK_JSON), (&bin, CHUNK_BIN)] {
        out.extend_from_slice(&u32::try_from(chunk.len()).ok()?.to_le_bytes());
        out.extend_from_slice(&kind.to_le_bytes());
        out.extend_from_slice(chunk);
    }
    Some(out)
}

/// Pads `bytes` with `fill` to a multiple of 4 (chunks and buffer views are 4-byte aligned).
fn pad(bytes: &mut Vec<u8>, fill: u8) {
    while !bytes.len().is_multiple_of(4) {
        bytes.push(fill);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::ply::{MeshParams, build_mesh};
    use crate::vision::Image;

    fn u32_at(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    /// Splits a GLB into its JSON and binary chunk, checking the container.
    fn chunks(glb: &[u8]) -> (serde_json::Value, &[u8]) {
        assert_eq!(u32_at(glb, 0), MAGIC);
        assert_eq!(u32_at(glb, 4), 2);
        assert_eq!(u32_at(glb, 8) as usize, glb.len());
        let json_len = u32_at(glb, 12) as usize;
        assert_eq!(u32_at(glb, 16), CHUNK_JSON);
        assert_eq!(json_len % 4, 0);
        let json = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
        let at = 20 + json_len;
        let bin_len = u32_at(glb, at) as usize;
        assert_eq!(u32_at(glb, at + 4), CHUNK_BIN);
        assert_eq!(at + 8 + bin_len, glb.len());
        (json, &glb[at + 8..])
    }

    #[test]
    fn a_mesh_round_trips_through_the_glb_layout() {
        let height = Image::from_fn(4, 3, |x, y| x as f32 * 0.05 + y as f32 * 0.1);
        let intensity = Image::filled(4, 3, 0.5);
        let mesh = build_mesh(&height, 0.1, Some(&intensity), &MeshParams::default());
        let glb = mesh_glb(&mesh, "test").unwrap();
        let (json, bin) = chunks(&glb);
        assert_eq!(
            json["buffers"][0]["byteLength"].as_u64().unwrap() as usize % 4,
            0
        );
        let acc = &json["accessors"];
        assert_eq!(acc[0]["count"], mesh.vertices.len());
        assert_eq!(acc[2]["count"], mesh.triangles.len() * 3);
        assert_eq!(acc[2]["componentType"], UNSIGNED_SHORT);
        for (i, view) in json["bufferViews"].as_array().unwrap().iter().enumerate() {
            let (offset, len) = (
                view["byteOffset"].as_u64().unwrap() as usize,
                view["byteLength"].as_u64().unwrap() as usize,
            );
            assert_eq!(offset % 4, 0, "view {i}");
            assert!(offset + len <= bin.len(), "view {i}");
        }
        // Vertex 5 is column 1, row 1: export (0.1, −0.1, 0.15) → glTF (0.1, 0.15, 0.1).
        let p: Vec<f32> = (0..3)
            .map(|k| f32::from_le_bytes(bin[60 + 4 * k..64 + 4 * k].try_into().unwrap()))
            .collect();
        let v = mesh.vertices[5];
        assert_eq!(p, [v.x, v.z, -v.y]);
        assert!(
            (p[1] - 0.15).abs() < 1e-6 && (p[2] - 0.1).abs() < 1e-6,
            "{p:?}"
        );
        // min/max bound the positions; the height is glTF's y.
        assert!((acc[0]["max"][1].as_f64().unwrap() - 0.35).abs() < 1e-6);
        // Grey 0.5 → 128, opaque.
        let colours = &bin[mesh.vertices.len() * 12..];
        assert_eq!(&colours[..4], &[128, 128, 128, 255]);
        // The first triangle's indices read back.
        let idx_at = json["bufferViews"][2]["byteOffset"].as_u64().unwrap() as usize;
        let first: Vec<u32> = (0..3)
            .map(|k| {
                u32::from(u16::from_le_bytes([
                    bin[idx_at + 2 * k],
                    bin[idx_at + 2 * k + 1],
                ]))
            })
            .collect();
        assert_eq!(first, mesh.triangles[0]);
    }

    #[test]
    fn many_vertices_take_32_bit_indices_and_no_triangles_no_file() {
        let height = Image::from_fn(300, 300, |x, _| x as f32 * 0.01);
        let mesh = build_mesh(&height, 0.1, None, &MeshParams::default());
        let glb = mesh_glb(&mesh, "test").unwrap();
        let (json, _) = chunks(&glb);
        assert_eq!(json["accessors"][2]["componentType"], UNSIGNED_INT);
        let lone = build_mesh(&Image::filled(1, 1, 0.0), 0.1, None, &MeshParams::default());
        assert!(mesh_glb(&lone, "test").is_none());
    }
}
