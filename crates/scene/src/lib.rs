//! Scene description for cvfarm.
//!
//! Data flows one way: a scene file (native JSON [`desc::SceneDesc`] or Mitsuba 3 XML, which
//! [`mitsuba`] imports into a `SceneDesc`) is loaded by [`load`] into a validated [`Scene`]
//! (assets read through an [`AssetSource`], transforms applied, references resolved), and
//! [`Features`] summarises which effects the scene calls for so that the renderer builds only
//! those.
//!
//! # Layout
//! - [`desc`]: the native JSON format (serde types, user docs per feature).
//! - [`model`]: the loaded scene the renderer consumes.
//! - `mitsuba`: Mitsuba 3 XML → `SceneDesc`.
//! - `load`: `SceneDesc` + assets → `Scene`, with validation.
//! - `features`: the `Features` summary.

pub mod desc;
pub mod model;

pub use desc::SceneDesc;
pub use model::*;
