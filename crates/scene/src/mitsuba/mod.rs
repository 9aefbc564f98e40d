//! Mitsuba 3 XML import: a Mitsuba scene file → [`SceneDesc`].
//!
//! Supported subset (anything else is an error naming the element and its line — never a
//! silent skip):
//!
//! | element | types | parameters |
//! |---|---|---|
//! | `<integrator>` | `path` | `max_depth` (−1), `rr_depth` (5), `hide_emitters` (false) |
//! | `<sensor>` | `perspective` | `fov`, `fov_axis` (x), `focal_length` (50mm when no fov), `near_clip` (0.01), `far_clip` (10000), `to_world` |
//! | `<film>` | `hdrfilm` | `width` (768), `height` (576); `pixel_format`, `component_format`, `file_format`, `sample_border`, `banner` accepted and ignored; `<rfilter type="box">` — another filter (or none: Mitsuba's default is gaussian) is rendered with a box filter and reported as a warning |
//! | `<sampler>` | any | `sample_count` (recorded as `integrator.sample_count`), `seed` ignored |
//! | `<shape>` | `obj`, `ply`, `rectangle`, `cube`, `sphere` | `filename`, `face_normals`, `flip_normals`, `to_world`, sphere `center`/`radius`; obj `flip_tex_coords` must stay true; nested `<bsdf>`, `<emitter type="area">`, `<ref id>` |
//! | `<bsdf>` | `diffuse`, `conductor`, `roughconductor`, `roughplastic`, `twosided` | colours as `<rgb>` (1 or 3 values), single-value `<spectrum>`, `<float>`, `<texture>`, `<ref>`; `eta`/`k` constant; `distribution` (beckmann default), `alpha` (0.1) or equal `alpha_u`/`alpha_v`; `int_ior`/`ext_ior` as numbers or Mitsuba's named IORs; `sample_visible` ignored |
//! | `<texture>` | `bitmap`, `checkerboard` | `filename`, `raw`, `filter_type`, `wrap_mode`, `to_uv`; `color0`, `color1` |
//! | `<emitter>` | `area` (in a shape or by id), `envmap`, `constant` | `radiance`; `filename`, `scale`, `to_world` |
//! | `<transform>` | — | `translate`, `scale`, `rotate`, `lookat`, `matrix` |
//! | `<default>`, `<include>`, `$param` | | substitution in every attribute; caller parameters override defaults |
//!
//! Conventions kept from Mitsuba: a conductor without `eta`/`k` (material `none`) is a perfect
//! mirror (eta 0, k 1); the default integrator depth is −1 (unbounded); `to_uv` is applied to
//! the point (u, v, 0) as in Mitsuba 3.9 (so the native `uv_transform` takes it unchanged).

pub mod xml;

use std::collections::{BTreeMap, HashMap};

use crate::desc::*;
use crate::{AssetSource, SceneError};
use xml::Node;

/// Imports a Mitsuba 3 XML scene. Includes and mesh names stay relative names (read through
/// `assets` when loading); `params` override `<default>` values.
pub fn import(
    xml: &str,
    assets: &dyn AssetSource,
    params: &[(String, String)],
) -> Result<SceneDesc, SceneError> {
    import_with_warnings(xml, "scene.xml", assets, params).map(|(d, _)| d)
}

/// [`import`] that also returns the importer's warnings; `file` names the document in errors.
pub fn import_with_warnings(
    xml: &str,
    file: &str,
    assets: &dyn AssetSource,
    params: &[(String, String)],
) -> Result<(SceneDesc, Vec<String>), SceneError> {
    let params: BTreeMap<String, String> = params.iter().cloned().collect();
    let root = xml::parse_scene(xml, file, assets, &params)?;
    let mut imp = Importer {
        ids: HashMap::new(),
        textures: BTreeMap::new(),
        warnings: Vec::new(),
        tex_counter: 0,
    };
    for c in &root.children {
        if let Some(id) = c.attr("id")
            && imp.ids.insert(id.to_string(), c).is_some()
        {
            return Err(c.error(format!("duplicate id {id:?}")));
        }
    }
    let desc = imp.scene(&root)?;
    Ok((desc, imp.warnings))
}

// ---------------------------------------------------------------------------------------------
// values

fn numbers(node: &Node, key: &str) -> Result<Vec<f32>, SceneError> {
    let s = node
        .attr(key)
        .ok_or_else(|| node.error(format!("missing attribute `{key}`")))?;
    let mut out = Vec::new();
    for w in s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|w| !w.is_empty())
    {
        let v: f32 = w
            .parse()
            .map_err(|_| node.error(format!("`{key}`: cannot parse {w:?} as a number")))?;
        if !v.is_finite() {
            return Err(node.error(format!("`{key}`: non-finite value {w:?}")));
        }
        out.push(v);
    }
    Ok(out)
}

fn number(node: &Node, key: &str) -> Result<f32, SceneError> {
    match numbers(node, key)?.as_slice() {
        [v] => Ok(*v),
        v => Err(node.error(format!("`{key}`: expected one number, found {}", v.len()))),
    }
}

fn opt_number(node: &Node, key: &str, default: f32) -> Result<f32, SceneError> {
    if node.attr(key).is_some() {
        number(node, key)
    } else {
        Ok(default)
    }
}

fn vec3(node: &Node, key: &str) -> Result<[f32; 3], SceneError> {
    match numbers(node, key)?.as_slice() {
        [x, y, z] => Ok([*x, *y, *z]),
        v => Err(node.error(format!("`{key}`: expected 3 numbers, found {}", v.len()))),
    }
}

/// `x="" y="" z=""` attributes or a `value="x y z"`.
fn xyz(node: &Node, default: f32) -> Result<[f32; 3], SceneError> {
    if node.attr("value").is_some() {
        return vec3(node, "value");
    }
    Ok([
        opt_number(node, "x", default)?,
        opt_number(node, "y", default)?,
        opt_number(node, "z", default)?,
    ])
}

fn parse_transform(node: &Node) -> Result<TransformDesc, SceneError> {
    let mut ops = Vec::new();
    for c in &node.children {
        ops.push(match c.tag.as_str() {
            "translate" => TransformOp::Translate(xyz(c, 0.0)?),
            "scale" => {
                if c.attr("value").is_some() {
                    match numbers(c, "value")?.as_slice() {
                        [s] => TransformOp::Scale([*s; 3]),
                        [x, y, z] => TransformOp::Scale([*x, *y, *z]),
                        _ => return Err(c.error("`value`: expected 1 or 3 numbers")),
                    }
                } else {
                    TransformOp::Scale(xyz(c, 1.0)?)
                }
            }
            "rotate" => TransformOp::Rotate {
                axis: xyz(c, 0.0)?,
                angle: number(c, "angle")?,
            },
            "lookat" => TransformOp::LookAt {
                origin: vec3(c, "origin")?,
                target: vec3(c, "target")?,
                up: if c.attr("up").is_some() {
                    vec3(c, "up")?
                } else {
                    [0.0, 1.0, 0.0]
                },
            },
            "matrix" => match numbers(c, "value")?.as_slice() {
                v if v.len() == 16 => {
                    let mut m = [0.0; 16];
                    m.copy_from_slice(v);
                    TransformOp::Matrix(m)
                }
                v if v.len() == 9 => {
                    let mut m = [0.0; 16];
                    for r in 0..3 {
                        for k in 0..3 {
                            m[4 * r + k] = v[3 * r + k];
                        }
                    }
                    m[15] = 1.0;
                    TransformOp::Matrix(m)
                }
                v => {
                    return Err(c.error(format!(
                        "`value`: expected 16 (or 9) numbers, found {}",
                        v.len()
                    )));
                }
            },
            _ => return Err(c.error("unsupported transform operation")),
        });
        // Validate each step as we go so that errors point at the XML line.
        crate::transform::to_matrix(&ops[ops.len() - 1..].to_vec(), "transform")
            .map_err(|e| c.error(e.to_string()))?;
    }
    Ok(ops)
}

/// Mitsuba's named IORs (`int_ior="bk7"`), from its documentation table.
fn named_ior(name: &str) -> Option<f32> {
    Some(match name {
        "vacuum" => 1.0,
        "helium" => 1.000_036,
        "hydrogen" => 1.000_132,
        "air" => 1.000_277,
        "carbon dioxide" => 1.000_45,
        "water" => 1.333,
        "acetone" => 1.36,
        "ethanol" => 1.361,
        "carbon tetrachloride" => 1.461,
        "glycerol" => 1.4729,
        "benzene" => 1.501,
        "silicone oil" => 1.520_45,
        "bromine" => 1.661,
        "water ice" => 1.31,
        "fused quartz" => 1.458,
        "pyrex" => 1.470,
        "acrylic glass" => 1.490,
        "polypropylene" => 1.49,
        "bk7" => 1.5046,
        "sodium chloride" => 1.544,
        "amber" => 1.55,
        "pet" => 1.575,
        "diamond" => 2.419,
        _ => return None,
    })
}

// ---------------------------------------------------------------------------------------------
// property bags

const VALUE_TAGS: &[&str] = &[
    "float",
    "integer",
    "boolean",
    "string",
    "rgb",
    "spectrum",
    "point",
    "vector",
    "transform",
    "ref",
    "texture",
];

/// The named properties of one plugin element; tracks which were read so that leftovers are
/// reported as unsupported.
struct Props<'n> {
    owner: &'n Node,
    items: Vec<(&'n str, &'n Node, bool)>,
    /// Children without a `name`: nested plugins (`bsdf`, `emitter`, `film`, ...) and `ref`s.
    nested: Vec<&'n Node>,
}

impl<'n> Props<'n> {
    fn of(owner: &'n Node) -> Result<Self, SceneError> {
        let mut items: Vec<(&'n str, &'n Node, bool)> = Vec::new();
        let mut nested = Vec::new();
        for c in &owner.children {
            match c.attr("name") {
                // Exporters name nested plugins and refs to them (`<ref name="bsdf" id=".."/>`):
                // those stay nested objects, not parameters.
                Some(name)
                    if VALUE_TAGS.contains(&c.tag.as_str())
                        && !(c.tag == "ref" && (name.starts_with("bsdf") || name == "emitter")) =>
                {
                    if items.iter().any(|(n, _, _)| *n == name) {
                        return Err(c.error(format!("parameter `{name}` given twice")));
                    }
                    items.push((name, c, false));
                }
                _ => nested.push(c),
            }
        }
        Ok(Self {
            owner,
            items,
            nested,
        })
    }

    fn take(&mut self, name: &str) -> Option<&'n Node> {
        self.items
            .iter_mut()
            .find(|(n, _, _)| *n == name)
            .map(|(_, node, used)| {
                *used = true;
                *node
            })
    }

    fn float(&mut self, name: &str) -> Result<Option<f32>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) if n.tag == "float" || n.tag == "integer" => number(n, "value").map(Some),
            Some(n) => Err(n.error(format!(
                "`{name}` must be a <float> (textured parameters are not supported)"
            ))),
        }
    }

    fn int(&mut self, name: &str) -> Result<Option<i64>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) if n.tag == "integer" => {
                let s = n.attr("value").ok_or_else(|| n.error("missing `value`"))?;
                s.trim()
                    .parse()
                    .map(Some)
                    .map_err(|_| n.error(format!("cannot parse {s:?} as an integer")))
            }
            Some(n) => Err(n.error(format!("`{name}` must be an <integer>"))),
        }
    }

    fn boolean(&mut self, name: &str) -> Result<Option<bool>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) if n.tag == "boolean" => {
                match n.attr("value").map(str::to_ascii_lowercase).as_deref() {
                    Some("true") | Some("1") => Ok(Some(true)),
                    Some("false") | Some("0") => Ok(Some(false)),
                    other => Err(n.error(format!("`value` must be true or false, not {other:?}"))),
                }
            }
            Some(n) => Err(n.error(format!("`{name}` must be a <boolean>"))),
        }
    }

    fn string(&mut self, name: &str) -> Result<Option<(String, &'n Node)>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) if n.tag == "string" => Ok(Some((
                n.attr("value")
                    .ok_or_else(|| n.error("missing `value`"))?
                    .to_string(),
                n,
            ))),
            Some(n) => Err(n.error(format!("`{name}` must be a <string>"))),
        }
    }

    fn transform(&mut self, name: &str) -> Result<TransformDesc, SceneError> {
        match self.take(name) {
            None => Ok(Vec::new()),
            Some(n) if n.tag == "transform" => parse_transform(n),
            Some(n) => Err(n.error(format!("`{name}` must be a <transform>"))),
        }
    }

    /// A constant colour (`<rgb>`, single-value `<spectrum>`, `<float>`).
    fn rgb(&mut self, name: &str) -> Result<Option<[f32; 3]>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) => constant_color(n).map(Some),
        }
    }

    fn ior(&mut self, name: &str) -> Result<Option<f32>, SceneError> {
        match self.take(name) {
            None => Ok(None),
            Some(n) if n.tag == "string" => {
                let v = n.attr("value").unwrap_or_default();
                named_ior(&v.to_ascii_lowercase())
                    .map(Some)
                    .ok_or_else(|| n.error(format!("unknown IOR name {v:?}")))
            }
            Some(n) if n.tag == "float" || n.tag == "integer" => number(n, "value").map(Some),
            Some(n) => Err(n.error(format!(
                "`{name}` must be a <float> or a named IOR <string>"
            ))),
        }
    }

    /// Errors on the first named property that was not read, unless listed in `ignored`.
    fn finish(&self, ignored: &[&str]) -> Result<(), SceneError> {
        for (name, node, used) in &self.items {
            if !used && !ignored.contains(name) {
                return Err(node.error(format!(
                    "unsupported parameter `{name}` of <{}>",
                    self.owner.describe()
                )));
            }
        }
        Ok(())
    }
}

fn constant_color(n: &Node) -> Result<[f32; 3], SceneError> {
    match n.tag.as_str() {
        "rgb" => match numbers(n, "value")?.as_slice() {
            [v] => Ok([*v; 3]),
            [r, g, b] => Ok([*r, *g, *b]),
            v => Err(n.error(format!("<rgb> needs 1 or 3 values, found {}", v.len()))),
        },
        "spectrum" => {
            if n.attr("filename").is_some() {
                return Err(
                    n.error("spectra from files are not supported; write the colour as <rgb>")
                );
            }
            let s = n.attr("value").unwrap_or_default();
            if s.contains(':') {
                return Err(
                    n.error("per-wavelength spectra are not supported; write the colour as <rgb>")
                );
            }
            Ok([number(n, "value")?; 3])
        }
        "float" | "integer" => Ok([number(n, "value")?; 3]),
        _ => Err(n.error("expected a constant colour (<rgb>, <spectrum value=\"x\"> or <float>)")),
    }
}

// ---------------------------------------------------------------------------------------------
// the importer

struct Importer<'n> {
    ids: HashMap<String, &'n Node>,
    textures: BTreeMap<String, TextureDesc>,
    warnings: Vec<String>,
    tex_counter: usize,
}

fn plugin_type(n: &Node) -> Result<&str, SceneError> {
    n.attr("type").ok_or_else(|| n.error("missing `type`"))
}

impl<'n> Importer<'n> {
    fn lookup(&self, r: &'n Node) -> Result<&'n Node, SceneError> {
        let id = r.attr("id").ok_or_else(|| r.error("<ref> needs an `id`"))?;
        self.ids
            .get(id)
            .copied()
            .ok_or_else(|| r.error(format!("no top-level object with id {id:?}")))
    }

    fn scene(&mut self, root: &'n Node) -> Result<SceneDesc, SceneError> {
        let mut camera_film: Option<(CameraDesc, FilmDesc, Option<u32>)> = None;
        // Mitsuba's path integrator defaults: unbounded depth, RR from depth 5.
        let mut integrator = IntegratorDesc {
            max_depth: -1,
            ..IntegratorDesc::default()
        };
        let mut materials = BTreeMap::new();
        let mut shapes = Vec::new();
        let mut environment = None;
        for c in &root.children {
            match c.tag.as_str() {
                "default" => {}
                "integrator" => integrator = self.integrator(c)?,
                "sensor" => {
                    if camera_film.is_some() {
                        return Err(c.error("more than one sensor"));
                    }
                    camera_film = Some(self.sensor(c)?);
                }
                "bsdf" => match c.attr("id") {
                    Some(id) => {
                        let m = self.bsdf(c)?;
                        materials.insert(id.to_string(), m);
                    }
                    None => self.warnings.push(format!(
                        "{}:{}: top-level <bsdf> without id is unused",
                        c.file, c.line
                    )),
                },
                "texture" => {
                    let id = c
                        .attr("id")
                        .ok_or_else(|| c.error("a top-level <texture> needs an `id`"))?;
                    let t = self.texture(c)?;
                    self.textures.insert(id.to_string(), t);
                }
                "emitter" => match plugin_type(c)? {
                    "area" => {
                        if c.attr("id").is_none() {
                            return Err(c.error("an area emitter must be nested in a <shape> (or have an id that a shape references)"));
                        }
                    }
                    _ => {
                        if environment.is_some() {
                            return Err(
                                c.error("more than one environment emitter (envmap/constant)")
                            );
                        }
                        environment = Some(self.environment(c)?);
                    }
                },
                "shape" => shapes.push(self.shape(c)?),
                _ => return Err(c.error("unsupported element at scene level")),
            }
        }
        let Some((camera, film, sample_count)) = camera_film else {
            return Err(root.error("the scene has no <sensor>"));
        };
        integrator.sample_count = sample_count;
        Ok(SceneDesc {
            camera,
            film,
            integrator,
            textures: std::mem::take(&mut self.textures),
            materials,
            shapes,
            environment,
        })
    }

    fn integrator(&mut self, n: &'n Node) -> Result<IntegratorDesc, SceneError> {
        if plugin_type(n)? != "path" {
            return Err(n.error("only the `path` integrator is supported"));
        }
        let mut p = Props::of(n)?;
        if let Some(c) = p.nested.first() {
            return Err(c.error("unexpected nested element in <integrator>"));
        }
        let mut d = IntegratorDesc {
            max_depth: -1,
            ..IntegratorDesc::default()
        };
        if let Some(v) = p.int("max_depth")? {
            d.max_depth = i32::try_from(v).map_err(|_| n.error("max_depth out of range"))?;
        }
        if let Some(v) = p.int("rr_depth")? {
            d.rr_depth = i32::try_from(v).map_err(|_| n.error("rr_depth out of range"))?;
        }
        if let Some(v) = p.boolean("hide_emitters")? {
            d.hide_emitters = v;
        }
        p.finish(&[])?;
        Ok(d)
    }

    fn sensor(&mut self, n: &'n Node) -> Result<(CameraDesc, FilmDesc, Option<u32>), SceneError> {
        if plugin_type(n)? != "perspective" {
            return Err(n.error("only the `perspective` sensor is supported"));
        }
        let mut p = Props::of(n)?;
        let fov = p.float("fov")?;
        let focal = p.string("focal_length")?;
        let (fov, fov_axis) = match (fov, focal) {
            (Some(_), Some((_, f))) => {
                return Err(f.error("give either `fov` or `focal_length`, not both"));
            }
            (Some(f), None) => {
                let axis = match p.string("fov_axis")? {
                    None => FovAxis::X,
                    Some((s, node)) => match s.to_ascii_lowercase().as_str() {
                        "x" => FovAxis::X,
                        "y" => FovAxis::Y,
                        "diagonal" => FovAxis::Diagonal,
                        "smaller" => FovAxis::Smaller,
                        "larger" => FovAxis::Larger,
                        _ => return Err(node.error(format!("unknown fov_axis {s:?}"))),
                    },
                };
                (f, axis)
            }
            (None, focal) => {
                // A 35 mm film back (36 × 24 mm): the focal length fixes the diagonal fov.
                let mm = match focal {
                    None => 50.0,
                    Some((s, node)) => s
                        .trim()
                        .trim_end_matches("mm")
                        .trim()
                        .parse::<f32>()
                        .ok()
                        .filter(|v| v.is_finite() && *v > 0.0)
                        .ok_or_else(|| node.error(format!("cannot parse focal_length {s:?}")))?,
                };
                let diag = (36.0f32 * 36.0 + 24.0 * 24.0).sqrt();
                (
                    (2.0 * (diag / (2.0 * mm)).atan()).to_degrees(),
                    FovAxis::Diagonal,
                )
            }
        };
        let near_clip = p.float("near_clip")?.unwrap_or(0.01);
        let far_clip = p.float("far_clip")?.unwrap_or(10_000.0);
        let transform = p.transform("to_world")?;
        p.finish(&[])?;
        let mut film = None;
        let mut sample_count = None;
        for c in &p.nested {
            match c.tag.as_str() {
                "film" => film = Some(self.film(c)?),
                "sampler" => {
                    let mut sp = Props::of(c)?;
                    let count = sp.int("sample_count")?.unwrap_or(4);
                    if !(1..=i64::from(u32::MAX)).contains(&count) {
                        return Err(c.error("sample_count must be ≥ 1"));
                    }
                    sample_count = Some(count as u32);
                    sp.finish(&["seed"])?;
                }
                _ => return Err(c.error("unsupported element in <sensor>")),
            }
        }
        let film = match film {
            Some(f) => f,
            None => {
                self.warnings.push(format!(
                    "{}:{}: sensor has no <film>: using Mitsuba's default 768x576 (box filter)",
                    n.file, n.line
                ));
                FilmDesc {
                    width: 768,
                    height: 576,
                }
            }
        };
        Ok((
            CameraDesc {
                fov,
                fov_axis,
                transform,
                near_clip,
                far_clip,
            },
            film,
            sample_count,
        ))
    }

    fn film(&mut self, n: &'n Node) -> Result<FilmDesc, SceneError> {
        if plugin_type(n)? != "hdrfilm" {
            return Err(n.error("only `hdrfilm` is supported"));
        }
        let mut p = Props::of(n)?;
        let side = |v: Option<i64>, default: u32, node: &Node| -> Result<u32, SceneError> {
            match v {
                None => Ok(default),
                Some(v) => u32::try_from(v)
                    .ok()
                    .filter(|v| *v > 0)
                    .ok_or_else(|| node.error("film size must be ≥ 1")),
            }
        };
        let width = side(p.int("width")?, 768, n)?;
        let height = side(p.int("height")?, 576, n)?;
        p.finish(&[
            "pixel_format",
            "component_format",
            "file_format",
            "sample_border",
            "banner",
        ])?;
        let mut box_filter = false;
        for c in &p.nested {
            if c.tag != "rfilter" {
                return Err(c.error("unsupported element in <film>"));
            }
            if plugin_type(c)? == "box" {
                box_filter = true;
            } else {
                self.warnings.push(format!(
                    "{}:{}: rfilter {:?} is not supported; cvfarm renders with a box filter",
                    c.file,
                    c.line,
                    c.attr("type").unwrap_or_default()
                ));
            }
        }
        if !box_filter && !p.nested.iter().any(|c| c.tag == "rfilter") {
            self.warnings.push(format!(
                "{}:{}: film has no <rfilter> (Mitsuba's default is gaussian); cvfarm renders with a box filter",
                n.file, n.line
            ));
        }
        Ok(FilmDesc { width, height })
    }

    /// A colour parameter: constant, nested `<texture>` or `<ref>` to a top-level texture.
    fn color(&mut self, p: &mut Props<'n>, name: &str) -> Result<Option<ColorDesc>, SceneError> {
        let Some(n) = p.take(name) else {
            return Ok(None);
        };
        match n.tag.as_str() {
            "texture" => {
                let t = self.texture(n)?;
                self.tex_counter += 1;
                let key = match n.attr("id") {
                    Some(id) => id.to_string(),
                    None => format!("_tex{}", self.tex_counter),
                };
                self.textures.insert(key.clone(), t);
                Ok(Some(ColorDesc::Texture { texture: key }))
            }
            "ref" => {
                let target = self.lookup(n)?;
                if target.tag != "texture" {
                    return Err(n.error(format!(
                        "`{name}` refers to a <{}>, expected a <texture>",
                        target.tag
                    )));
                }
                let id = target.attr("id").unwrap_or_default().to_string();
                if !self.textures.contains_key(&id) {
                    let t = self.texture(target)?;
                    self.textures.insert(id.clone(), t);
                }
                Ok(Some(ColorDesc::Texture { texture: id }))
            }
            _ => {
                let c = constant_color(n)?;
                Ok(Some(if c[0] == c[1] && c[1] == c[2] {
                    ColorDesc::Gray(c[0])
                } else {
                    ColorDesc::Rgb(c)
                }))
            }
        }
    }

    fn texture(&mut self, n: &'n Node) -> Result<TextureDesc, SceneError> {
        let mut p = Props::of(n)?;
        if let Some(c) = p.nested.first() {
            return Err(c.error("unexpected nested element in <texture>"));
        }
        let t = match plugin_type(n)? {
            "bitmap" => {
                let (filename, _) = p
                    .string("filename")?
                    .ok_or_else(|| n.error("bitmap needs a `filename`"))?;
                let filter = match p.string("filter_type")? {
                    None => TextureFilter::Bilinear,
                    Some((s, _)) if s == "bilinear" => TextureFilter::Bilinear,
                    Some((s, _)) if s == "nearest" => TextureFilter::Nearest,
                    Some((s, node)) => return Err(node.error(format!("unknown filter_type {s:?}"))),
                };
                let wrap = match p.string("wrap_mode")? {
                    None => TextureWrap::Repeat,
                    Some((s, node)) => match s.as_str() {
                        "repeat" => TextureWrap::Repeat,
                        "mirror" => TextureWrap::Mirror,
                        "clamp" => TextureWrap::Clamp,
                        _ => return Err(node.error(format!("unknown wrap_mode {s:?}"))),
                    },
                };
                let raw = p.boolean("raw")?.unwrap_or(false);
                let uv_transform = self.uv_transform(&mut p)?;
                TextureDesc::Bitmap {
                    filename,
                    raw,
                    filter,
                    wrap,
                    uv_transform,
                }
            }
            "checkerboard" => {
                let color0 = p.rgb("color0")?.unwrap_or([0.4; 3]);
                let color1 = p.rgb("color1")?.unwrap_or([0.2; 3]);
                let uv_transform = self.uv_transform(&mut p)?;
                TextureDesc::Checkerboard {
                    color0,
                    color1,
                    uv_transform,
                }
            }
            _ => return Err(n.error("unsupported texture type (bitmap and checkerboard are)")),
        };
        p.finish(&[])?;
        Ok(t)
    }

    /// Mitsuba's `to_uv`: Mitsuba 3.9 applies the 4×4 to (u, v, 0, 1) (a `translate` moves the
    /// pattern — checked against Mitsuba 3.9.1), which is the native semantics: passed through.
    fn uv_transform(&mut self, p: &mut Props<'n>) -> Result<TransformDesc, SceneError> {
        p.transform("to_uv")
    }

    fn bsdf(&mut self, n: &'n Node) -> Result<MaterialDesc, SceneError> {
        let mut p = Props::of(n)?;
        let ty = plugin_type(n)?;
        if ty != "twosided"
            && let Some(c) = p.nested.first()
        {
            return Err(c.error(format!("unexpected nested element in <bsdf type=\"{ty}\">")));
        }
        let distribution = |p: &mut Props<'n>| -> Result<Distribution, SceneError> {
            match p.string("distribution")? {
                None => Ok(Distribution::Beckmann),
                Some((s, node)) => match s.as_str() {
                    "beckmann" => Ok(Distribution::Beckmann),
                    "ggx" => Ok(Distribution::Ggx),
                    _ => Err(node.error(format!("unknown distribution {s:?}"))),
                },
            }
        };
        let alpha = |p: &mut Props<'n>| -> Result<f32, SceneError> {
            let a = p.float("alpha")?;
            let (au, av) = (p.float("alpha_u")?, p.float("alpha_v")?);
            match (a, au, av) {
                (Some(a), None, None) => Ok(a),
                (None, None, None) => Ok(0.1),
                (None, Some(u), Some(v)) if u == v => Ok(u),
                _ => Err(n.error("anisotropic roughness (alpha_u ≠ alpha_v) is not supported")),
            }
        };
        let conductor_material = |p: &mut Props<'n>| -> Result<(), SceneError> {
            match p.string("material")? {
                Some((s, node)) if s != "none" => Err(node.error(format!(
                    "named conductor material {s:?} is not supported; give `eta` and `k` as <rgb>"
                ))),
                _ => Ok(()),
            }
        };
        let m = match ty {
            "diffuse" => MaterialDesc::Diffuse {
                reflectance: self.color(&mut p, "reflectance")?.unwrap_or(ColorDesc::Gray(0.5)),
            },
            "conductor" => {
                conductor_material(&mut p)?;
                MaterialDesc::Conductor {
                    eta: p.rgb("eta")?.unwrap_or([0.0; 3]),
                    k: p.rgb("k")?.unwrap_or([1.0; 3]),
                    specular_reflectance: self.color(&mut p, "specular_reflectance")?.unwrap_or(ColorDesc::Gray(1.0)),
                }
            }
            "roughconductor" => {
                conductor_material(&mut p)?;
                MaterialDesc::RoughConductor {
                    distribution: distribution(&mut p)?,
                    alpha: alpha(&mut p)?,
                    eta: p.rgb("eta")?.unwrap_or([0.0; 3]),
                    k: p.rgb("k")?.unwrap_or([1.0; 3]),
                    specular_reflectance: self.color(&mut p, "specular_reflectance")?.unwrap_or(ColorDesc::Gray(1.0)),
                }
            }
            "roughplastic" => MaterialDesc::RoughPlastic {
                distribution: distribution(&mut p)?,
                alpha: alpha(&mut p)?,
                int_ior: p.ior("int_ior")?.unwrap_or(1.49),
                ext_ior: p.ior("ext_ior")?.unwrap_or(1.000_277),
                diffuse_reflectance: self.color(&mut p, "diffuse_reflectance")?.unwrap_or(ColorDesc::Gray(0.5)),
                specular_reflectance: self.color(&mut p, "specular_reflectance")?.unwrap_or(ColorDesc::Gray(1.0)),
                nonlinear: p.boolean("nonlinear")?.unwrap_or(false),
            },
            "twosided" => {
                let mut inner = Vec::new();
                for c in p.nested.clone() {
                    match c.tag.as_str() {
                        "bsdf" => inner.push(self.bsdf(c)?),
                        "ref" => {
                            let target = self.lookup(c)?;
                            if target.tag != "bsdf" {
                                return Err(c.error("<ref> in a twosided bsdf must name a <bsdf>"));
                            }
                            inner.push(self.bsdf(target)?);
                        }
                        _ => return Err(c.error("unexpected element in a twosided bsdf")),
                    }
                }
                match inner.len() {
                    1 => MaterialDesc::TwoSided { bsdf: Box::new(inner.remove(0)) },
                    0 => return Err(n.error("twosided needs one nested <bsdf>")),
                    _ => return Err(n.error("different BSDFs per side are not supported")),
                }
            }
            _ => return Err(n.error("unsupported BSDF type (diffuse, conductor, roughconductor, roughplastic, twosided are)")),
        };
        p.finish(&["sample_visible"])?;
        Ok(m)
    }

    fn area_emitter(&mut self, n: &'n Node) -> Result<AreaEmitterDesc, SceneError> {
        if plugin_type(n)? != "area" {
            return Err(n.error("only `area` emitters can be attached to shapes"));
        }
        let mut p = Props::of(n)?;
        if let Some(c) = p.nested.first() {
            return Err(c.error("unexpected nested element in <emitter>"));
        }
        let radiance = p
            .rgb("radiance")?
            .ok_or_else(|| n.error("area emitter needs a constant `radiance`"))?;
        p.finish(&[])?;
        Ok(AreaEmitterDesc { radiance })
    }

    fn environment(&mut self, n: &'n Node) -> Result<EnvironmentDesc, SceneError> {
        let mut p = Props::of(n)?;
        if let Some(c) = p.nested.first() {
            return Err(c.error("unexpected nested element in <emitter>"));
        }
        let e = match plugin_type(n)? {
            "envmap" => EnvironmentDesc::Envmap {
                filename: p
                    .string("filename")?
                    .ok_or_else(|| n.error("envmap needs a `filename`"))?
                    .0,
                scale: p.float("scale")?.unwrap_or(1.0),
                transform: p.transform("to_world")?,
            },
            "constant" => EnvironmentDesc::Constant {
                radiance: p.rgb("radiance")?.unwrap_or([1.0; 3]),
            },
            _ => return Err(n.error("unsupported emitter type (area, envmap, constant are)")),
        };
        p.finish(&[])?;
        Ok(e)
    }

    fn shape(&mut self, n: &'n Node) -> Result<ShapeDesc, SceneError> {
        let mut p = Props::of(n)?;
        let ty = plugin_type(n)?;
        let geometry = match ty {
            "obj" | "ply" => {
                let filename = p
                    .string("filename")?
                    .ok_or_else(|| n.error("needs a `filename`"))?
                    .0;
                let face_normals = p.boolean("face_normals")?.unwrap_or(false);
                if ty == "obj" {
                    if p.boolean("flip_tex_coords")? == Some(false) {
                        return Err(n.error("flip_tex_coords=false is not supported"));
                    }
                    GeometryDesc::Obj {
                        filename,
                        face_normals,
                    }
                } else {
                    GeometryDesc::Ply {
                        filename,
                        face_normals,
                    }
                }
            }
            "rectangle" => GeometryDesc::Rectangle,
            "cube" => GeometryDesc::Cube,
            "sphere" => {
                let center = match p.take("center") {
                    None => [0.0; 3],
                    Some(c) if c.tag == "point" || c.tag == "vector" => xyz(c, 0.0)?,
                    Some(c) => return Err(c.error("`center` must be a <point>")),
                };
                GeometryDesc::Sphere {
                    center,
                    radius: p.float("radius")?.unwrap_or(1.0),
                }
            }
            _ => {
                return Err(
                    n.error("unsupported shape type (obj, ply, rectangle, cube, sphere are)")
                );
            }
        };
        let transform = p.transform("to_world")?;
        let flip_normals = p.boolean("flip_normals")?.unwrap_or(false);
        let mut material = None;
        let mut emitter = None;
        for c in p.nested.clone() {
            let (target, by_ref) = if c.tag == "ref" {
                (self.lookup(c)?, true)
            } else {
                (c, false)
            };
            match target.tag.as_str() {
                "bsdf" => {
                    if material.is_some() {
                        return Err(c.error("a shape can have only one bsdf"));
                    }
                    material = Some(if by_ref {
                        MaterialRef::Named(target.attr("id").unwrap_or_default().to_string())
                    } else {
                        MaterialRef::Inline(self.bsdf(target)?)
                    });
                }
                "emitter" => {
                    if emitter.is_some() {
                        return Err(c.error("a shape can have only one emitter"));
                    }
                    emitter = Some(self.area_emitter(target)?);
                }
                _ => return Err(c.error("unsupported element in <shape>")),
            }
        }
        p.finish(&[])?;
        Ok(ShapeDesc {
            geometry,
            material,
            transform,
            emitter,
            flip_normals,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::MemoryAssets;

    fn imp(body: &str) -> Result<SceneDesc, SceneError> {
        let xml = format!(
            "<scene version=\"3.0.0\"><sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>\
             <film type=\"hdrfilm\"><integer name=\"width\" value=\"32\"/><integer name=\"height\" value=\"16\"/>\
             <rfilter type=\"box\"/></film></sensor>{body}</scene>"
        );
        import(&xml, &MemoryAssets::new(), &[])
    }

    #[test]
    fn defaults_follow_mitsuba() {
        let d = imp("<shape type=\"cube\"><bsdf type=\"conductor\"/></shape>").unwrap();
        assert_eq!(d.integrator.max_depth, -1);
        assert_eq!(
            d.film,
            FilmDesc {
                width: 32,
                height: 16
            }
        );
        let Some(MaterialRef::Inline(MaterialDesc::Conductor { eta, k, .. })) =
            &d.shapes[0].material
        else {
            panic!("{:?}", d.shapes[0].material)
        };
        assert_eq!((*eta, *k), ([0.0; 3], [1.0; 3]));
    }

    #[test]
    fn unknown_things_are_errors_with_lines() {
        for (body, needle) in [
            ("<shape type=\"disk\"/>", "unsupported shape type"),
            (
                "<shape type=\"cube\"><bsdf type=\"dielectric\"/></shape>",
                "unsupported BSDF",
            ),
            (
                "<shape type=\"cube\"><float name=\"wobble\" value=\"1\"/></shape>",
                "unsupported parameter `wobble`",
            ),
            ("<medium type=\"homogeneous\"/>", "unsupported element"),
            ("<emitter type=\"point\"/>", "unsupported emitter"),
            (
                "<shape type=\"cube\"><bsdf type=\"diffuse\"><spectrum name=\"reflectance\" value=\"400:0.1, 700:0.5\"/></bsdf></shape>",
                "per-wavelength",
            ),
            (
                "<shape type=\"cube\"><transform name=\"to_world\"><rotate angle=\"3\"/></transform></shape>",
                "zero vector",
            ),
            (
                "<shape type=\"cube\"><transform name=\"to_world\"><translate x=\"nan\"/></transform></shape>",
                "non-finite",
            ),
        ] {
            let e = imp(body).unwrap_err().to_string();
            assert!(e.contains(needle), "{body}: {e}");
            assert!(e.starts_with("scene.xml:1:"), "{e}");
        }
    }

    #[test]
    fn named_nested_plugins_and_refs() {
        let d = imp(
            "<bsdf type=\"diffuse\" id=\"w\"/>\
             <shape type=\"cube\"><ref name=\"bsdf\" id=\"w\"/></shape>\
             <shape type=\"cube\"><bsdf type=\"twosided\" name=\"bsdf\"><ref name=\"bsdf_0\" id=\"w\"/></bsdf></shape>",
        )
        .unwrap();
        assert_eq!(d.shapes[0].material, Some(MaterialRef::Named("w".into())));
        assert!(matches!(
            d.shapes[1].material,
            Some(MaterialRef::Inline(MaterialDesc::TwoSided { .. }))
        ));
    }

    #[test]
    fn textures_and_refs() {
        let d = imp(
            "<texture type=\"checkerboard\" id=\"checks\"><rgb name=\"color0\" value=\"0.9\"/>\
             <transform name=\"to_uv\"><scale x=\"4\" y=\"4\"/></transform></texture>\
             <bsdf type=\"twosided\" id=\"mat\"><bsdf type=\"diffuse\"><ref name=\"reflectance\" id=\"checks\"/></bsdf></bsdf>\
             <shape type=\"rectangle\"><ref id=\"mat\"/></shape>\
             <shape type=\"cube\"><bsdf type=\"diffuse\"><texture name=\"reflectance\" type=\"bitmap\">\
             <string name=\"filename\" value=\"t.png\"/><transform name=\"to_uv\"><translate x=\"0.5\"/></transform></texture></bsdf></shape>",
        )
        .unwrap();
        assert_eq!(d.shapes[0].material, Some(MaterialRef::Named("mat".into())));
        assert!(matches!(
            d.textures["checks"],
            TextureDesc::Checkerboard {
                color0: [0.9, 0.9, 0.9],
                ..
            }
        ));
        // Mitsuba 3.9 applies a to_uv translate (checked with Mitsuba 3.9.1).
        let TextureDesc::Bitmap { uv_transform, .. } = &d.textures["_tex1"] else {
            panic!()
        };
        let m = crate::transform::to_matrix(uv_transform, "t").unwrap();
        assert_eq!(
            m.transform_point3(glam::Vec3::new(0.25, 0.5, 0.0)),
            glam::Vec3::new(0.75, 0.5, 0.0)
        );
    }
}
