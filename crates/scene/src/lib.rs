//! Scene description for cvfarm.
//!
//! Data flows one way: a scene file (native JSON [`desc::SceneDesc`] or Mitsuba 3 XML, which
//! [`mitsuba`] imports into a `SceneDesc`) is loaded by [`load()`] into a validated [`Scene`]
//! (assets read through an [`AssetSource`], transforms applied, references resolved), and
//! [`Features`] summarises which effects the scene calls for so that the renderer builds only
//! those.
//!
//! ```no_run
//! let loaded = scene::load_file(std::path::Path::new("scenes/cbox/scene.xml"))?;
//! let features = scene::Features::of(&loaded.scene);
//! println!("{} emitters, dropped {} triangles", features.emitters, loaded.report.dropped_triangles);
//! # Ok::<(), scene::SceneError>(())
//! ```
//!
//! # Layout
//! - [`desc`]: the native JSON format (serde types, user docs per feature).
//! - [`model`]: the loaded scene the renderer consumes.
//! - [`mitsuba`]: Mitsuba 3 XML → `SceneDesc` (`xml` submodule: element tree, `$param`, `<include>`).
//! - [`mod@load`]: `SceneDesc` + assets → `Scene`, with validation and the [`LoadReport`].
//! - [`features`]: the [`Features`] summary.
//! - [`assets`]: [`AssetSource`], [`DirAssets`], [`MemoryAssets`].
//! - [`meshfile`]: OBJ and PLY readers, Mitsuba's built-in `rectangle` and `cube`.
//! - [`transform`]: transform lists → matrices (Mitsuba semantics).
//! - [`error`]: [`SceneError`], [`AssetError`].

#![deny(missing_docs)]

pub mod assets;
pub mod desc;
pub mod error;
pub mod features;
pub mod load;
pub mod meshfile;
pub mod mitsuba;
pub mod model;
pub mod transform;

use std::path::Path;

pub use assets::{AssetSource, DirAssets, MemoryAssets};
pub use desc::SceneDesc;
pub use error::{AssetError, SceneError};
pub use features::{BsdfKind, EnvironmentKind, Features};
pub use load::{DroppedTriangles, LoadReport, LoadedScene, load};
pub use model::*;

/// Parses a native JSON scene. Errors carry the line and column.
pub fn from_json_str(json: &str) -> Result<SceneDesc, SceneError> {
    serde_json::from_str(json).map_err(|e| SceneError::Json {
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    })
}

/// Serialises a scene description as pretty-printed native JSON (round-trips through
/// [`from_json_str`]).
pub fn to_json_string(desc: &SceneDesc) -> String {
    // Serialising plain data structs with string keys cannot fail.
    serde_json::to_string_pretty(desc).unwrap_or_default()
}

/// Reads a scene description from a file: `.json` (native) or `.xml` (Mitsuba 3, with
/// `params` overriding `<default>`s). Returns the description and the importer's warnings.
pub fn read_desc_file(
    path: &Path,
    params: &[(String, String)],
) -> Result<(SceneDesc, Vec<String>), SceneError> {
    let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let dir = path.parent().unwrap_or(Path::new("."));
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("json") => Ok((from_json_str(&text)?, Vec::new())),
        Some("xml") => {
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            mitsuba::import_with_warnings(&text, &name, &DirAssets::new(dir), params)
        }
        _ => Err(SceneError::UnknownFormat {
            path: path.to_path_buf(),
        }),
    }
}

/// Loads a scene file (`.json` native or `.xml` Mitsuba 3); assets are resolved relative to the
/// file's directory. Importer warnings are included in the report.
pub fn load_file(path: &Path) -> Result<LoadedScene, SceneError> {
    load_file_with_params(path, &[])
}

/// [`load_file`] with Mitsuba `$param` values (ignored for JSON).
pub fn load_file_with_params(
    path: &Path,
    params: &[(String, String)],
) -> Result<LoadedScene, SceneError> {
    let (desc, warnings) = read_desc_file(path, params)?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut loaded = load(&desc, &DirAssets::new(dir))?;
    let mut all = warnings;
    all.append(&mut loaded.report.warnings);
    loaded.report.warnings = all;
    Ok(loaded)
}
