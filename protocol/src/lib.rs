//! Canopy's wire types and their codec: species graphs (the DCG programs of seed 001), limits, encoding.
//!
//! Contract: this crate holds data and the rules for accepting it, nothing else. It depends on no tokio, quinn,
//! wgpu or filesystem; every decoder bounds sizes, counts and depth before it allocates or recurses, and
//! [`species::SpeciesGraph::decode`] returns only graphs that pass [`species::SpeciesGraph::validate`].

pub mod aoi;
pub mod edit;
pub mod expr;
pub mod farview;
pub mod frame;
mod grant;
pub mod hypertree;
pub mod limits;
pub mod lru;
pub mod messages;
pub mod netlimits;
pub mod record;
pub mod species;
pub mod summary;
pub mod sync;
mod world;
pub mod xorshift;

pub use expr::{Expr, Func, Op};
pub use messages::{ALPN, ClientMsg, CloseCode, MessageError, PROTOCOL_VERSION, Phase, ServerMsg, SpeciesHash};
pub use record::{CellBatch, CellCoord, InstanceId, InstanceRecord, POSITION_STEPS};
pub use species::{
    DecodeError, LeafTopology, Node, NodeId, ParamDecl, ParamRole, ParamScope, SpeciesGraph, ValidateError,
};
