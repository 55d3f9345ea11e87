//! The renderer's clock: `std::time::Instant` natively; in a browser (wasm32, where `Instant::now` panics) the
//! page's `performance.now()`, with the same `now`, `elapsed` and `duration_since`.

#[cfg(not(target_arch = "wasm32"))]
pub(crate) use std::time::Instant;

#[cfg(target_arch = "wasm32")]
pub(crate) use web::Instant;

#[cfg(target_arch = "wasm32")]
mod web {
    use std::time::Duration;

    /// A moment on the page's monotonic clock, milliseconds since the page's time origin.
    #[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
    pub(crate) struct Instant(f64);

    /// `performance.now()`, or 0 where there is no window (a worker without one is not supported).
    fn millis() -> f64 {
        web_sys::window().and_then(|w| w.performance()).map_or(0.0, |p| p.now())
    }

    impl Instant {
        /// Now.
        pub(crate) fn now() -> Instant {
            Instant(millis())
        }

        /// The time since `earlier` (zero if it is later).
        pub(crate) fn duration_since(&self, earlier: Instant) -> Duration {
            Duration::from_secs_f64(((self.0 - earlier.0) / 1e3).max(0.0))
        }

        /// The time since this instant.
        pub(crate) fn elapsed(&self) -> Duration {
            Instant::now().duration_since(*self)
        }
    }
}
