//! Shared helpers for Canopy's integration tests (the tests themselves live in `tests/tests/`).
