//! Stanford PLY reader: ASCII, binary little endian and binary big endian.
//!
//! Contract: vertex element with `x y z` (any numeric type), optional `nx ny nz` and texture
//! coordinates `u v`, `s t` or `texture_u texture_v` (**not** flipped, as in Mitsuba); a face
//! element with a list property `vertex_indices` or `vertex_index`, polygons triangulated as
//! fans. Other elements and properties are skipped. Errors name the file and the header line or
//! element/item. Counts are checked against the file size before allocating.

use glam::{Vec2, Vec3};

use super::RawMesh;
use crate::SceneError;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

#[derive(Clone, Debug)]
enum Property {
    Scalar {
        name: String,
        ty: Scalar,
    },
    List {
        name: String,
        count: Scalar,
        item: Scalar,
    },
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Le,
    Be,
}

enum Body<'a> {
    Ascii(std::str::SplitAsciiWhitespace<'a>),
    Binary {
        data: &'a [u8],
        pos: usize,
        big: bool,
    },
}

impl Body<'_> {
    fn read(&mut self, ty: Scalar) -> Option<f64> {
        match self {
            Body::Ascii(tokens) => tokens.next()?.parse::<f64>().ok(),
            Body::Binary { data, pos, big } => {
                let n = ty.size();
                let bytes = data.get(*pos..*pos + n)?;
                *pos += n;
                let mut b = [0u8; 8];
                b[..n].copy_from_slice(bytes);
                if *big {
                    b[..n].reverse();
                }
                Some(match ty {
                    Scalar::I8 => f64::from(b[0] as i8),
                    Scalar::U8 => f64::from(b[0]),
                    Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
                    Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
                    Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::F64 => f64::from_le_bytes(b),
                })
            }
        }
    }
}

/// Parses a PLY file. `file` is the asset name used in errors.
pub fn parse(file: &str, bytes: &[u8]) -> Result<RawMesh, SceneError> {
    let err = |location: String, message: String| SceneError::Mesh {
        file: file.to_string(),
        location,
        message,
    };
    // --- header
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(end) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(err("header".into(), "no end_header line".into()));
        };
        let line = std::str::from_utf8(&bytes[pos..pos + end])
            .map_err(|_| err(format!("header line {}", line_no + 1), "not UTF-8".into()))?
            .trim();
        pos += end + 1;
        line_no += 1;
        let at = format!("header line {line_no}");
        let w: Vec<&str> = line.split_whitespace().collect();
        if line_no == 1 {
            if line != "ply" {
                return Err(err(at, "not a PLY file (first line must be `ply`)".into()));
            }
            continue;
        }
        match w.first().copied() {
            Some("format") => {
                format = Some(match w.get(1).copied() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::Le,
                    Some("binary_big_endian") => Format::Be,
                    other => return Err(err(at, format!("unknown format {other:?}"))),
                })
            }
            Some("comment") | Some("obj_info") | None => {}
            Some("element") => {
                let (Some(name), Some(count)) = (w.get(1), w.get(2).and_then(|c| c.parse().ok()))
                else {
                    return Err(err(at, format!("bad element line {line:?}")));
                };
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let Some(el) = elements.last_mut() else {
                    return Err(err(at, "property before any element".into()));
                };
                let prop = if w.get(1) == Some(&"list") {
                    match (
                        w.get(2).and_then(|s| Scalar::parse(s)),
                        w.get(3).and_then(|s| Scalar::parse(s)),
                        w.get(4),
                    ) {
                        (Some(count), Some(item), Some(name)) => Property::List {
                            name: name.to_string(),
                            count,
                            item,
                        },
                        _ => return Err(err(at, format!("bad list property {line:?}"))),
                    }
                } else {
                    match (w.get(1).and_then(|s| Scalar::parse(s)), w.get(2)) {
                        (Some(ty), Some(name)) => Property::Scalar {
                            name: name.to_string(),
                            ty,
                        },
                        _ => return Err(err(at, format!("bad property {line:?}"))),
                    }
                };
                el.props.push(prop);
            }
            Some("end_header") => break,
            Some(other) => return Err(err(at, format!("unknown header keyword {other:?}"))),
        }
    }
    let Some(format) = format else {
        return Err(err("header".into(), "missing format line".into()));
    };
    let data = &bytes[pos..];
    // Sanity-check counts against the data size (each item needs at least one byte / token).
    let min_bytes: usize = elements
        .iter()
        .map(|e| {
            let per: usize = e
                .props
                .iter()
                .map(|p| match p {
                    Property::Scalar { ty, .. } => ty.size(),
                    Property::List { count, .. } => count.size(),
                })
                .sum();
            e.count.saturating_mul(if format == Format::Ascii {
                per.min(1)
            } else {
                per
            })
        })
        .fold(0usize, usize::saturating_add);
    if min_bytes > data.len() {
        return Err(err(
            "body".into(),
            format!(
                "header promises at least {min_bytes} bytes, file has {}",
                data.len()
            ),
        ));
    }
    let mut body = match format {
        Format::Ascii => Body::Ascii(
            std::str::from_utf8(data)
                .map_err(|_| err("body".into(), "ASCII body is not UTF-8".into()))?
                .split_ascii_whitespace(),
        ),
        Format::Le => Body::Binary {
            data,
            pos: 0,
            big: false,
        },
        Format::Be => Body::Binary {
            data,
            pos: 0,
            big: true,
        },
    };

    let mut mesh = RawMesh::default();
    let mut normals: Vec<Vec3> = Vec::new();
    let mut uvs: Vec<Vec2> = Vec::new();
    let mut saw_vertex = false;
    let mut saw_face = false;
    for el in &elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        saw_vertex |= is_vertex;
        saw_face |= is_face;
        let find = |names: &[&str]| {
            el.props.iter().position(
                |p| matches!(p, Property::Scalar { name, .. } if names.contains(&name.as_str())),
            )
        };
        let (ix, iy, iz) = (find(&["x"]), find(&["y"]), find(&["z"]));
        let (inx, iny, inz) = (find(&["nx"]), find(&["ny"]), find(&["nz"]));
        let (iu, iv) = (
            find(&["u", "s", "texture_u", "texture_s"]),
            find(&["v", "t", "texture_v", "texture_t"]),
        );
        if is_vertex && (ix.is_none() || iy.is_none() || iz.is_none()) {
            return Err(err(
                "element vertex".into(),
                "needs x, y and z properties".into(),
            ));
        }
        let has_n = inx.is_some() && iny.is_some() && inz.is_some();
        let has_uv = iu.is_some() && iv.is_some();
        let face_list = el.props.iter().position(
            |p| matches!(p, Property::List { name, .. } if name == "vertex_indices" || name == "vertex_index"),
        );
        if is_face && face_list.is_none() {
            return Err(err(
                "element face".into(),
                "needs a list property vertex_indices".into(),
            ));
        }
        let cap = el.count.min(1 << 20);
        if is_vertex {
            mesh.positions.reserve(cap);
        }
        let mut values = vec![0.0f64; el.props.len()];
        let mut list: Vec<f64> = Vec::new();
        for item in 0..el.count {
            let at = || format!("element {}, item {item}", el.name);
            for (k, p) in el.props.iter().enumerate() {
                match p {
                    Property::Scalar { ty, .. } => {
                        values[k] = body
                            .read(*ty)
                            .ok_or_else(|| err(at(), "truncated or malformed value".into()))?;
                    }
                    Property::List {
                        count, item: ity, ..
                    } => {
                        let n = body
                            .read(*count)
                            .ok_or_else(|| err(at(), "truncated list length".into()))?;
                        if !(0.0..=1e6).contains(&n) || n.fract() != 0.0 {
                            return Err(err(at(), format!("bad list length {n}")));
                        }
                        let keep = Some(k) == face_list && is_face;
                        if keep {
                            list.clear();
                        }
                        for _ in 0..n as usize {
                            let x = body
                                .read(*ity)
                                .ok_or_else(|| err(at(), "truncated list".into()))?;
                            if keep {
                                list.push(x);
                            }
                        }
                    }
                }
            }
            if is_vertex {
                let g = |i: Option<usize>| values[i.unwrap_or(0)] as f32;
                mesh.positions.push(Vec3::new(g(ix), g(iy), g(iz)));
                if has_n {
                    normals.push(Vec3::new(g(inx), g(iny), g(inz)));
                }
                if has_uv {
                    uvs.push(Vec2::new(g(iu), g(iv)));
                }
            } else if is_face {
                if list.len() < 3 {
                    return Err(err(at(), format!("face with {} vertices", list.len())));
                }
                let mut idx = Vec::with_capacity(list.len());
                for &x in &list {
                    if x < 0.0 || x.fract() != 0.0 || x >= mesh.positions.len() as f64 {
                        return Err(err(
                            at(),
                            format!(
                                "vertex index {x} out of range (0..{})",
                                mesh.positions.len()
                            ),
                        ));
                    }
                    idx.push(x as u32);
                }
                for k in 1..idx.len() - 1 {
                    mesh.indices.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
        }
    }
    if !saw_vertex || !saw_face || mesh.indices.is_empty() {
        return Err(err("body".into(), "no vertex or face data".into()));
    }
    if !normals.is_empty() {
        mesh.normals = Some(normals);
    }
    if !uvs.is_empty() {
        mesh.uvs = Some(uvs);
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(format: &str) -> String {
        format!(
            "ply\nformat {format} 1.0\ncomment test\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
             property float s\nproperty float t\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        )
    }

    fn binary(big: bool) -> Vec<u8> {
        let mut b = header(if big {
            "binary_big_endian"
        } else {
            "binary_little_endian"
        })
        .into_bytes();
        let verts = [
            [0.0f32, 0.0, 0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 1.0, 0.0],
            [1.0, 1.0, 0.0, 1.0, 1.0],
            [0.0, 1.0, 0.0, 0.0, 1.0],
        ];
        for v in verts {
            for x in v {
                b.extend(if big {
                    x.to_be_bytes()
                } else {
                    x.to_le_bytes()
                });
            }
        }
        b.push(4);
        for i in 0..4i32 {
            b.extend(if big {
                i.to_be_bytes()
            } else {
                i.to_le_bytes()
            });
        }
        b
    }

    #[test]
    fn ascii_le_and_be_agree() {
        let ascii = header("ascii") + "0 0 0 0 0\n1 0 0 1 0\n1 1 0 1 1\n0 1 0 0 1\n4 0 1 2 3\n";
        let a = parse("a.ply", ascii.as_bytes()).unwrap();
        let le = parse("le.ply", &binary(false)).unwrap();
        let be = parse("be.ply", &binary(true)).unwrap();
        assert_eq!(a, le);
        assert_eq!(a, be);
        assert_eq!(a.indices, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(a.uvs.as_ref().unwrap()[2], Vec2::new(1.0, 1.0)); // not flipped
    }

    #[test]
    fn truncated_and_bad_files_are_errors() {
        let b = binary(false);
        for cut in [0, 3, 20, b.len() - 30, b.len() - 1] {
            assert!(parse("t.ply", &b[..cut]).is_err(), "cut {cut}");
        }
        let mut bad = binary(false);
        let n = bad.len();
        bad[n - 4..].copy_from_slice(&9i32.to_le_bytes());
        let e = parse("i.ply", &bad).unwrap_err().to_string();
        assert!(
            e.contains("element face, item 0") && e.contains("out of range"),
            "{e}"
        );
        let huge = "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nend_header\n";
        assert!(parse("h.ply", huge.as_bytes()).is_err());
    }
}
