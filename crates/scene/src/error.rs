//! Typed errors of the scene crate. Every message names *where* the problem is: a JSON
//! line/column, an XML element and line, a mesh file and line, or a field path such as
//! `shapes[3].transform[1].rotate.axis`.

use std::path::PathBuf;

/// Failure to read an asset through an [`crate::AssetSource`].
#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    /// No asset of that name.
    #[error("asset {name:?} not found")]
    NotFound {
        /// The relative asset name.
        name: String,
    },
    /// The name is absolute, empty or escapes the asset root (`..`).
    #[error(
        "invalid asset name {name:?}: names are relative and may not leave the scene directory"
    )]
    InvalidName {
        /// The offending name.
        name: String,
    },
    /// The file exists but could not be read.
    #[error("asset {name:?}: {source}")]
    Io {
        /// The relative asset name.
        name: String,
        /// Underlying I/O error.
        source: std::io::Error,
    },
}

/// Everything that can go wrong between a scene file and a [`crate::Scene`].
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The native JSON document is malformed or does not match the format.
    #[error("scene JSON, line {line}, column {column}: {message}")]
    Json {
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What serde reported.
        message: String,
    },
    /// The XML is not well formed.
    #[error("{file}: XML syntax error at line {line}: {message}")]
    Xml {
        /// Scene or included file name.
        file: String,
        /// 1-based line.
        line: usize,
        /// What the parser reported.
        message: String,
    },
    /// A Mitsuba element cvfarm does not support, or an invalid value in one.
    #[error("{file}:{line}: <{element}>: {message}")]
    Mitsuba {
        /// Scene or included file name.
        file: String,
        /// 1-based line of the element.
        line: usize,
        /// The element, e.g. `bsdf type="dielectric"`.
        element: String,
        /// What is wrong.
        message: String,
    },
    /// An asset could not be read.
    #[error(transparent)]
    Asset(#[from] AssetError),
    /// A mesh file is malformed.
    #[error("mesh {file}: {location}: {message}")]
    Mesh {
        /// Asset name of the mesh.
        file: String,
        /// `line N` (OBJ, ASCII PLY) or `element E, item I` / `header` (PLY).
        location: String,
        /// What is wrong.
        message: String,
    },
    /// An image asset could not be decoded.
    #[error("image {file}: {source}")]
    Image {
        /// Asset name of the image.
        file: String,
        /// Decoder error.
        source: imageio::ImageError,
    },
    /// A value fails validation; `path` names the field, e.g. `shapes[3].transform[1].rotate.axis`.
    #[error("{path}: {message}")]
    Invalid {
        /// Field path in the native format.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// A scene file could not be read from disk.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The scene file's extension is neither `.json` nor `.xml`.
    #[error("{path}: unknown scene format (expected .json or .xml)")]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
}

impl SceneError {
    /// Shorthand for [`SceneError::Invalid`].
    pub fn invalid(path: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }
}
