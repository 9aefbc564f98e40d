//! A minimal XML element tree with line numbers (quick-xml underneath), `$param`
//! substitution and `<include>` expansion — the syntax layer of the Mitsuba importer.

use std::collections::BTreeMap;

use quick_xml::Reader;
use quick_xml::events::{BytesStart, Event};

use crate::{AssetSource, SceneError};

/// Maximum `<include>` nesting (guards against include cycles).
pub const MAX_INCLUDE_DEPTH: usize = 16;

/// Maximum element nesting (real scenes use < 10; bounds recursion on hostile input).
pub const MAX_DEPTH: usize = 64;

/// One XML element.
#[derive(Clone, Debug, PartialEq)]
pub struct Node {
    /// Element name, e.g. `bsdf`.
    pub tag: String,
    /// Attributes in document order.
    pub attrs: Vec<(String, String)>,
    /// Child elements.
    pub children: Vec<Node>,
    /// 1-based line of the start tag.
    pub line: usize,
    /// File the element comes from (the scene or an included file).
    pub file: String,
}

impl Node {
    /// Attribute `key`, if present.
    pub fn attr(&self, key: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    /// Short description for errors: `bsdf type="dielectric" id="glass"`.
    pub fn describe(&self) -> String {
        let mut s = self.tag.clone();
        for key in ["type", "name", "id"] {
            if let Some(v) = self.attr(key) {
                s.push_str(&format!(" {key}=\"{v}\""));
            }
        }
        s
    }

    /// An importer error located at this element.
    pub fn error(&self, message: impl Into<String>) -> SceneError {
        SceneError::Mitsuba {
            file: self.file.clone(),
            line: self.line,
            element: self.describe(),
            message: message.into(),
        }
    }
}

fn line_of(src: &str, pos: usize) -> usize {
    src.as_bytes()[..pos.min(src.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        + 1
}

fn element(e: &BytesStart<'_>, src: &str, pos: usize, file: &str) -> Result<Node, SceneError> {
    let line = line_of(src, pos);
    let xml_err = |message: String| SceneError::Xml {
        file: file.to_string(),
        line,
        message,
    };
    let tag = String::from_utf8_lossy(e.name().as_ref()).into_owned();
    let mut attrs = Vec::new();
    for a in e.attributes() {
        let a = a.map_err(|err| xml_err(err.to_string()))?;
        let key = String::from_utf8_lossy(a.key.as_ref()).into_owned();
        let value = a
            .unescape_value()
            .map_err(|err| xml_err(err.to_string()))?
            .into_owned();
        attrs.push((key, value));
    }
    Ok(Node {
        tag,
        attrs,
        children: Vec::new(),
        line,
        file: file.to_string(),
    })
}

/// Parses `src` into its root element. `file` names the document in errors.
pub fn parse(src: &str, file: &str) -> Result<Node, SceneError> {
    let mut reader = Reader::from_str(src);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<Node> = Vec::new();
    let mut root: Option<Node> = None;
    loop {
        let pos = reader.buffer_position() as usize;
        let event = reader.read_event().map_err(|e| SceneError::Xml {
            file: file.to_string(),
            line: line_of(src, reader.error_position() as usize),
            message: e.to_string(),
        })?;
        let mut finished: Option<Node> = None;
        match event {
            Event::Start(e) => {
                if stack.len() >= MAX_DEPTH {
                    return Err(SceneError::Xml {
                        file: file.to_string(),
                        line: line_of(src, pos),
                        message: format!("elements nested more than {MAX_DEPTH} deep"),
                    });
                }
                stack.push(element(&e, src, pos, file)?)
            }
            Event::Empty(e) => finished = Some(element(&e, src, pos, file)?),
            Event::End(_) => finished = stack.pop(),
            Event::Text(t) => {
                if !t.iter().all(u8::is_ascii_whitespace) {
                    return Err(SceneError::Xml {
                        file: file.to_string(),
                        line: line_of(src, pos),
                        message: "unexpected text content (Mitsuba scenes use attributes only)"
                            .into(),
                    });
                }
            }
            Event::CData(_) | Event::GeneralRef(_) => {
                return Err(SceneError::Xml {
                    file: file.to_string(),
                    line: line_of(src, pos),
                    message: "unexpected text content".into(),
                });
            }
            Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_) => {}
            Event::Eof => break,
        }
        if let Some(node) = finished {
            match stack.last_mut() {
                Some(parent) => parent.children.push(node),
                None if root.is_none() => root = Some(node),
                None => {
                    return Err(SceneError::Xml {
                        file: file.to_string(),
                        line: node.line,
                        message: "more than one root element".into(),
                    });
                }
            }
        }
    }
    if let Some(open) = stack.last() {
        return Err(SceneError::Xml {
            file: file.to_string(),
            line: open.line,
            message: format!("<{}> is never closed", open.tag),
        });
    }
    root.ok_or_else(|| SceneError::Xml {
        file: file.to_string(),
        line: 1,
        message: "empty document".into(),
    })
}

/// Replaces `$name` in `value` by `params[name]`; `None` names the first undefined parameter.
fn substitute_str(value: &str, params: &BTreeMap<String, String>) -> Result<String, String> {
    let mut out = String::with_capacity(value.len());
    let mut rest = value;
    while let Some(i) = rest.find('$') {
        out.push_str(&rest[..i]);
        let tail = &rest[i + 1..];
        let len = tail
            .bytes()
            .take_while(|b| b.is_ascii_alphanumeric() || *b == b'_')
            .count();
        if len == 0 {
            out.push('$');
            rest = tail;
            continue;
        }
        let name = &tail[..len];
        match params.get(name) {
            Some(v) => out.push_str(v),
            None => return Err(name.to_string()),
        }
        rest = &tail[len..];
    }
    out.push_str(rest);
    Ok(out)
}

fn substitute(node: &mut Node, params: &BTreeMap<String, String>) -> Result<(), SceneError> {
    if node.tag != "default" {
        for i in 0..node.attrs.len() {
            if node.attrs[i].1.contains('$') {
                let v = substitute_str(&node.attrs[i].1, params).map_err(|name| {
                    node.error(format!(
                        "parameter ${name} is not defined (no <default> and not given)"
                    ))
                })?;
                node.attrs[i].1 = v;
            }
        }
    }
    for c in &mut node.children {
        substitute(c, params)?;
    }
    Ok(())
}

/// Adds the `<default name value>` children of `scene` to `params` (existing entries win).
fn collect_defaults(scene: &Node, params: &mut BTreeMap<String, String>) -> Result<(), SceneError> {
    for c in scene.children.iter().filter(|c| c.tag == "default") {
        let (Some(name), Some(value)) = (c.attr("name"), c.attr("value")) else {
            return Err(c.error("<default> needs `name` and `value`"));
        };
        params
            .entry(name.to_string())
            .or_insert_with(|| value.to_string());
    }
    Ok(())
}

/// Parses a whole scene: root must be `<scene>`; defaults collected, `$params` substituted,
/// `<include filename>` elements replaced by the children of the included `<scene>` (read
/// through `assets`, names relative to the asset root).
pub fn parse_scene(
    src: &str,
    file: &str,
    assets: &dyn AssetSource,
    params: &BTreeMap<String, String>,
) -> Result<Node, SceneError> {
    let mut params = params.clone();
    expand(parse(src, file)?, assets, &mut params, 0)
}

fn expand(
    mut scene: Node,
    assets: &dyn AssetSource,
    params: &mut BTreeMap<String, String>,
    depth: usize,
) -> Result<Node, SceneError> {
    if scene.tag != "scene" {
        return Err(scene.error("the root element must be <scene>"));
    }
    collect_defaults(&scene, params)?;
    substitute(&mut scene, params)?;
    let children = std::mem::take(&mut scene.children);
    for c in children {
        if c.tag != "include" {
            scene.children.push(c);
            continue;
        }
        if depth >= MAX_INCLUDE_DEPTH {
            return Err(c.error("includes nested too deeply (cycle?)"));
        }
        let Some(name) = c.attr("filename") else {
            return Err(c.error("<include> needs a `filename`"));
        };
        let bytes = assets.read(name)?;
        let text =
            String::from_utf8(bytes).map_err(|_| c.error(format!("{name} is not UTF-8 text")))?;
        let sub = expand(parse(&text, name)?, assets, params, depth + 1)?;
        scene.children.extend(sub.children);
    }
    Ok(scene)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::MemoryAssets;

    #[test]
    fn lines_and_nesting() {
        let src = "<scene version=\"3.0.0\">\n  <shape type=\"cube\">\n    <bsdf type=\"diffuse\"/>\n  </shape>\n</scene>\n";
        let root = parse(src, "s.xml").unwrap();
        assert_eq!(root.children[0].line, 2);
        assert_eq!(root.children[0].children[0].line, 3);
        assert_eq!(
            root.children[0].children[0].describe(),
            "bsdf type=\"diffuse\""
        );
    }

    #[test]
    fn malformed_xml_reports_a_line() {
        let e = parse("<scene>\n<shape>\n</scene>", "bad.xml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad.xml") && e.contains("line"), "{e}");
        assert!(parse("", "e.xml").is_err());
        assert!(parse("<scene>\n<shape>", "u.xml").is_err());
    }

    #[test]
    fn deep_nesting_is_refused() {
        let src = "<a>".repeat(100_000);
        let e = parse(&src, "deep.xml").unwrap_err().to_string();
        assert!(e.contains("nested more than"), "{e}");
    }

    #[test]
    fn params_defaults_and_includes() {
        let assets = MemoryAssets::new()
            .with(
                "inc/part.xml",
                "<scene><shape type=\"$shape\"/></scene>"
                    .as_bytes()
                    .to_vec(),
            )
            .unwrap();
        let src = "<scene><default name=\"shape\" value=\"cube\"/><default name=\"spp\" value=\"8\"/>\
                   <integer name=\"x\" value=\"$spp\"/><include filename=\"inc/part.xml\"/></scene>";
        let mut params = BTreeMap::new();
        params.insert("spp".to_string(), "32".to_string());
        let root = parse_scene(src, "s.xml", &assets, &params).unwrap();
        assert_eq!(
            root.children[2].attr("value"),
            Some("32"),
            "caller params beat defaults"
        );
        assert_eq!(
            root.children[3].attr("type"),
            Some("cube"),
            "included file sees defaults"
        );
        let e = parse_scene(
            "<scene><float value=\"$nope\"/></scene>",
            "s.xml",
            &assets,
            &BTreeMap::new(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("$nope"), "{e}");
    }

    #[test]
    fn include_cycle_is_an_error() {
        let assets = MemoryAssets::new()
            .with(
                "a.xml",
                "<scene><include filename=\"a.xml\"/></scene>"
                    .as_bytes()
                    .to_vec(),
            )
            .unwrap();
        let e = parse_scene(
            "<scene><include filename=\"a.xml\"/></scene>",
            "s.xml",
            &assets,
            &BTreeMap::new(),
        );
        assert!(e.is_err());
    }
}
