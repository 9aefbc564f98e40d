//! Where asset bytes come from. A scene names its meshes, textures, env maps and included XML
//! files by **relative name** (`meshes/bunny.obj`); an [`AssetSource`] turns a name into bytes.
//!
//! - [`DirAssets`]: a directory on disk (the CLI). Names are resolved below the directory;
//!   absolute names and `..` components are rejected, so a scene cannot read outside it.
//! - [`MemoryAssets`]: a name → bytes map (the farm maps names to content-addressed blobs).
//!   It never touches the file system.
//!
//! Names use `/` as separator; a `\` is accepted and treated as `/`; `./` components are ignored.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::AssetError;

/// A source of asset bytes addressed by relative name.
pub trait AssetSource {
    /// The bytes of asset `name`.
    fn read(&self, name: &str) -> Result<Vec<u8>, AssetError>;
}

/// Normalises an asset name: `/` separators, no empty or `.` components; rejects absolute
/// names and `..`.
pub fn normalize_name(name: &str) -> Result<String, AssetError> {
    let invalid = || AssetError::InvalidName {
        name: name.to_string(),
    };
    let unified = name.replace('\\', "/");
    if unified.starts_with('/') || unified.contains(':') {
        return Err(invalid());
    }
    let mut parts = Vec::new();
    for part in unified.split('/') {
        match part {
            "" | "." => {}
            ".." => return Err(invalid()),
            p => parts.push(p),
        }
    }
    if parts.is_empty() {
        return Err(invalid());
    }
    Ok(parts.join("/"))
}

/// Assets in a directory on disk.
#[derive(Clone, Debug)]
pub struct DirAssets {
    root: PathBuf,
}

impl DirAssets {
    /// Assets below `root`.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    /// The directory.
    pub fn root(&self) -> &Path {
        &self.root
    }
}

impl AssetSource for DirAssets {
    fn read(&self, name: &str) -> Result<Vec<u8>, AssetError> {
        let rel = normalize_name(name)?;
        let path = self.root.join(&rel);
        std::fs::read(&path).map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => AssetError::NotFound { name: rel },
            _ => AssetError::Io { name: rel, source },
        })
    }
}

/// Assets held in memory, by normalised name. Never touches the file system.
#[derive(Clone, Debug, Default)]
pub struct MemoryAssets {
    files: BTreeMap<String, Vec<u8>>,
}

impl MemoryAssets {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds (or replaces) asset `name`.
    pub fn insert(&mut self, name: &str, bytes: impl Into<Vec<u8>>) -> Result<(), AssetError> {
        self.files.insert(normalize_name(name)?, bytes.into());
        Ok(())
    }

    /// Builder form of [`MemoryAssets::insert`].
    pub fn with(mut self, name: &str, bytes: impl Into<Vec<u8>>) -> Result<Self, AssetError> {
        self.insert(name, bytes)?;
        Ok(self)
    }

    /// Names held, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.files.keys().map(String::as_str)
    }
}

impl AssetSource for MemoryAssets {
    fn read(&self, name: &str) -> Result<Vec<u8>, AssetError> {
        let rel = normalize_name(name)?;
        self.files
            .get(&rel)
            .cloned()
            .ok_or(AssetError::NotFound { name: rel })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_normalised_and_escapes_rejected() {
        assert_eq!(normalize_name("./meshes//a.obj").unwrap(), "meshes/a.obj");
        assert_eq!(normalize_name("meshes\\a.obj").unwrap(), "meshes/a.obj");
        for bad in ["/etc/passwd", "../x", "a/../../x", "", ".", "C:/x"] {
            assert!(
                matches!(normalize_name(bad), Err(AssetError::InvalidName { .. })),
                "{bad}"
            );
        }
    }

    #[test]
    fn memory_assets_do_not_fall_back_to_disk() {
        let assets = MemoryAssets::new().with("a.txt", b"hi".to_vec()).unwrap();
        assert_eq!(assets.read("./a.txt").unwrap(), b"hi");
        // A file that certainly exists on disk is still unknown here.
        assert!(matches!(
            assets.read("Cargo.toml"),
            Err(AssetError::NotFound { .. })
        ));
    }

    #[test]
    fn dir_assets_read_below_root_only() {
        let assets = DirAssets::new(env!("CARGO_MANIFEST_DIR"));
        assert!(assets.read("Cargo.toml").is_ok());
        assert!(matches!(
            assets.read("nope.bin"),
            Err(AssetError::NotFound { .. })
        ));
        assert!(matches!(
            assets.read("../Cargo.toml"),
            Err(AssetError::InvalidName { .. })
        ));
    }
}
