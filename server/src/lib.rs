//! The Canopy world server. Today it only re-exports the species library it will serve; the world store, the
//! sans-IO session core and the QUIC driver arrive with the streaming issue.

pub use canopy_worlds as worlds;
