//! canopy-worlds' integration tests as one binary, a module a subject (one link instead of thirteen; cargo's own
//! advice for integration tests). `autotests = false` in `worlds/Cargo.toml`, so a new file here is compiled only
//! when it is named below; the house test (`tests/tests/house.rs`) fails on one that is not. The near-field LOD
//! chain's tests are their own target, `nearfield_lod`, because they need the `meshopt` feature.

mod baked;
mod cells;
mod check;
mod far;
mod files;
mod hypertree;
mod library;
mod lsystem;
mod lsystem_lpy;
mod nearfield;
mod nearfield_topology;
mod traversal;
mod typos;
mod world;
