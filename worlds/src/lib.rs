//! What Canopy worlds are made of: the text formats, the L-system→DCG compiler and pure, deterministic
//! amplification of species instances into primitives and meshes.
//!
//! Contract: nothing here reads the clock, the network or a GPU; the same species, seed, parameters and detail
//! level give bit-identical primitive streams and meshes on every platform (see `ARCHITECTURE.md`).

pub mod amplify;
pub mod diag;
mod eval;
mod expr;
pub mod fsread;
pub mod gltf;
pub mod hypertree;
pub mod library;
pub mod load;
pub mod lsystem;
pub mod mesh;
pub mod nearfield;
mod nodes;
pub mod primitive;
pub mod rng;
pub mod species_text;
mod text;
pub mod transform;
pub(crate) mod vec3;
pub mod world;
