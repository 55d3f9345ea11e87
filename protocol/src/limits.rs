//! Explicit limits on every size and count in a species graph, checked before allocation and on decode.

/// Largest encoded species graph accepted from the wire or a file, in bytes.
pub const MAX_SPECIES_BYTES: usize = 256 * 1024;
/// Most nodes in one species graph.
pub const MAX_NODES: usize = 65_536;
/// Most children of one group, separator, selection or LOD node.
pub const MAX_CHILDREN: usize = 4_096;
/// Most declared parameters (slots) of one species.
pub const MAX_PARAMS: usize = 4_096;
/// Most operations in one compiled expression.
pub const MAX_EXPR_OPS: usize = 1_024;
/// Deepest value stack one compiled expression may need.
pub const MAX_EXPR_STACK: usize = 64;
/// Most weights one `Choose` operation may take.
pub const MAX_CHOOSE: usize = 64;
/// Most points in one leaf polygon or strip.
pub const MAX_LEAF_POINTS: usize = 256;
/// Most assignments in one calculation node.
pub const MAX_ASSIGNMENTS: usize = 256;
/// Longest species or parameter name, in bytes.
pub const MAX_NAME_LEN: usize = 128;
