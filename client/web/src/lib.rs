//! Canopy in a browser: a page that connects to a `canopy-server` over WebTransport, speaks the same protocol as
//! the native client ([`canopy_client::state::ClientState`] driven as `canopy_client::net::Connection` drives it),
//! expands the cells it is granted on the page's thread a few at a time each animation frame, and draws a top-down
//! map of what it holds with a small HUD.
//!
//! The parts that need no browser are plain modules, tested natively: [`session`] (the sans-IO driver: frames in,
//! frames out, the bounded expansion), [`far`] (the far view's summary nodes computed in the page), [`camera`] (WASD
//! and mouse-look movement, scripted walks), [`page`] (the `connect.json` document, the state a test reads, the held
//! instances' digest) and [`map`] (the map's pixels).
//! The browser glue (WebTransport, the animation loop, input, the canvas) is in `web/`, built for wasm32 only.

pub mod camera;
mod far;
pub mod map;
pub mod page;
mod session;

#[cfg(target_arch = "wasm32")]
pub mod web;
