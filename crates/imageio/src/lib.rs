//! Image files for cvfarm: multi-layer OpenEXR read/write, PNG/JPEG decode, PNG preview.
