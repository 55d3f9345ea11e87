//! canopy-render's integration tests as one binary, a module a subject: the image tests on Mesa lavapipe (the far
//! field, the ground, leaves, the reference scenes, sun and wind, the GPU cull). `autotests = false` in `client/render/Cargo.toml`: a new
//! file here is compiled only when it is named below, which the house test checks.

mod cull;
mod fade;
mod far;
mod ground;
mod leaves;
mod render;
mod sun;
