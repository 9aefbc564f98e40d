//! Wavefront OBJ reader (the subset renderers use).
//!
//! Contract: returns a [`RawMesh`] in which a vertex is a unique (position, uv, normal) index
//! triple, as Mitsuba builds it; texture `v` is flipped (`1 − v`) as Mitsuba's `obj` does by
//! default; polygons are triangulated as fans around their first vertex. Normals are kept only if
//! *every* face vertex has one; uvs if any has one (like Mitsuba; the others get (0, 0), where Mitsuba leaves them uninitialised). Errors name the file and line. Statements other than
//! `v`, `vt`, `vn`, `f` (groups, materials, smoothing, lines, points) are ignored.

use std::collections::HashMap;

use glam::{Vec2, Vec3};

use super::RawMesh;
use crate::SceneError;

fn err(file: &str, line: usize, message: impl Into<String>) -> SceneError {
    SceneError::Mesh {
        file: file.to_string(),
        location: format!("line {line}"),
        message: message.into(),
    }
}

fn parse_f32s<const N: usize>(
    file: &str,
    line: usize,
    what: &str,
    words: &mut std::str::SplitWhitespace<'_>,
    min: usize,
) -> Result<[f32; N], SceneError> {
    let mut out = [0.0f32; N];
    let mut count = 0;
    for (i, w) in words.by_ref().enumerate() {
        if i >= N {
            break;
        }
        out[i] = w.parse().map_err(|_| {
            err(
                file,
                line,
                format!("{what}: cannot parse {w:?} as a number"),
            )
        })?;
        count += 1;
    }
    if count < min {
        return Err(err(
            file,
            line,
            format!("{what}: expected {min} numbers, found {count}"),
        ));
    }
    Ok(out)
}

/// Resolves a 1-based (or negative, relative) OBJ index against `len` items.
fn resolve(
    file: &str,
    line: usize,
    word: &str,
    len: usize,
    what: &str,
) -> Result<usize, SceneError> {
    let i: i64 = word
        .parse()
        .map_err(|_| err(file, line, format!("bad {what} index {word:?}")))?;
    let idx = if i > 0 {
        i - 1
    } else if i < 0 {
        len as i64 + i
    } else {
        -1
    };
    if idx < 0 || idx as usize >= len {
        return Err(err(
            file,
            line,
            format!("{what} index {i} out of range (1..={len})"),
        ));
    }
    Ok(idx as usize)
}

/// Parses an OBJ file. `file` is the asset name used in errors.
pub fn parse(file: &str, bytes: &[u8]) -> Result<RawMesh, SceneError> {
    let text =
        std::str::from_utf8(bytes).map_err(|e| err(file, 1, format!("not UTF-8 text: {e}")))?;
    let mut v: Vec<Vec3> = Vec::new();
    let mut vt: Vec<Vec2> = Vec::new();
    let mut vn: Vec<Vec3> = Vec::new();
    let mut map: HashMap<(usize, Option<usize>, Option<usize>), u32> = HashMap::new();
    let mut keys: Vec<(usize, Option<usize>, Option<usize>)> = Vec::new();
    let mut indices: Vec<[u32; 3]> = Vec::new();
    let mut any_uv = false;
    let mut all_n = true;

    for (ln, raw) in text.lines().enumerate() {
        let line = ln + 1;
        let content = raw.split('#').next().unwrap_or("");
        let mut words = content.split_whitespace();
        let Some(tag) = words.next() else { continue };
        match tag {
            "v" => v.push(Vec3::from(parse_f32s::<3>(file, line, "v", &mut words, 3)?)),
            "vt" => {
                let [a, b] = parse_f32s::<2>(file, line, "vt", &mut words, 1)?;
                vt.push(Vec2::new(a, 1.0 - b));
            }
            "vn" => vn.push(Vec3::from(parse_f32s::<3>(
                file, line, "vn", &mut words, 3,
            )?)),
            "f" => {
                let mut face: Vec<u32> = Vec::new();
                for w in words {
                    let mut parts = w.split('/');
                    let pv = resolve(file, line, parts.next().unwrap_or(""), v.len(), "vertex")?;
                    let pt = match parts.next() {
                        Some("") | None => None,
                        Some(s) => Some(resolve(file, line, s, vt.len(), "texture")?),
                    };
                    let pn = match parts.next() {
                        Some("") | None => None,
                        Some(s) => Some(resolve(file, line, s, vn.len(), "normal")?),
                    };
                    any_uv |= pt.is_some();
                    all_n &= pn.is_some();
                    let key = (pv, pt, pn);
                    let id = *map.entry(key).or_insert_with(|| {
                        keys.push(key);
                        (keys.len() - 1) as u32
                    });
                    face.push(id);
                }
                if face.len() < 3 {
                    return Err(err(
                        file,
                        line,
                        format!("face with {} vertices", face.len()),
                    ));
                }
                for k in 1..face.len() - 1 {
                    indices.push([face[0], face[k], face[k + 1]]);
                }
            }
            _ => {}
        }
    }
    if indices.is_empty() {
        return Err(SceneError::Mesh {
            file: file.to_string(),
            location: "end of file".into(),
            message: "no faces".into(),
        });
    }
    let positions = keys.iter().map(|k| v[k.0]).collect();
    // Like Mitsuba, uvs are kept if any face vertex has one; the others get (0, 0).
    let uvs = any_uv.then(|| {
        keys.iter()
            .map(|k| k.1.map_or(Vec2::ZERO, |t| vt[t]))
            .collect()
    });
    let normals = all_n.then(|| keys.iter().map(|k| vn[k.2.unwrap_or(0)]).collect());
    Ok(RawMesh {
        positions,
        normals,
        uvs,
        indices,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quad_with_uv_is_fanned_and_v_flipped() {
        let src = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0.25\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n";
        let m = parse("q.obj", src.as_bytes()).unwrap();
        assert_eq!(m.indices, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.uvs.as_ref().unwrap()[1], Vec2::new(1.0, 0.75));
        assert!(m.normals.is_none());
    }

    #[test]
    fn vertices_split_by_normal_and_negative_indices() {
        let src = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 0 -1\nf -3//1 -2//1 -1//1\nf 1//2 3//2 2//2\n";
        let m = parse("n.obj", src.as_bytes()).unwrap();
        assert_eq!(m.positions.len(), 6);
        assert_eq!(m.normals.as_ref().unwrap()[3], Vec3::NEG_Z);
    }

    #[test]
    fn errors_name_file_and_line() {
        let e = parse("bad.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 7\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("bad.obj") && e.contains("line 3") && e.contains("out of range"),
            "{e}"
        );
        let e = parse("bad.obj", b"v 0 zero 0\n").unwrap_err().to_string();
        assert!(e.contains("line 1"), "{e}");
        assert!(parse("e.obj", b"v 0 0 0\n").is_err());
        assert!(parse("z.obj", b"v 0 0 0\nf 0 0 0\n").is_err());
    }
}
