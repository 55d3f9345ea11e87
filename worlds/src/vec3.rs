//! 3-vector helpers, generic over `f32` (the mesher, the hypertree generator, voxeliser and CPU raymarcher) and
//! `f64` (the near field), with a fixed operation order (component by component, sums left to right, `libm`
//! square roots) so results are the same bits on every platform.

use std::ops::{Add, Mul, Sub};

/// A float the helpers work on: IEEE arithmetic and a `libm` square root.
pub(crate) trait Real: Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> {
    /// The square root, through `libm` (`sqrtf` or `sqrt`).
    fn sqrt(self) -> Self;
}

impl Real for f32 {
    #[inline]
    fn sqrt(self) -> f32 {
        libm::sqrtf(self)
    }
}

impl Real for f64 {
    #[inline]
    fn sqrt(self) -> f64 {
        libm::sqrt(self)
    }
}

/// `a + b`.
#[inline]
pub(crate) fn add<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a - b`.
#[inline]
pub(crate) fn sub<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a s`.
#[inline]
pub(crate) fn scale<T: Real>(a: [T; 3], s: T) -> [T; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Euclidean length: `sqrt(x·x + y·y + z·z)`, summed left to right.
#[inline]
pub(crate) fn norm<T: Real>(a: [T; 3]) -> T {
    dot(a, a).sqrt()
}

/// `a · b`, summed left to right.
#[inline]
pub(crate) fn dot<T: Real>(a: [T; 3], b: [T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`.
#[inline]
pub(crate) fn cross<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// `a / |a|` for rays and light directions; a zero vector is returned as it is.
#[inline]
pub(crate) fn unit(a: [f32; 3]) -> [f32; 3] {
    let n = norm(a);
    if n > 0.0 { a.map(|v| v / n) } else { a }
}

/// `v / |v|`, scaled by the largest component first so that huge or tiny vectors normalise too; `None` for a zero
/// or non-finite vector (the mesher's normals).
pub(crate) fn normalize(v: [f32; 3]) -> Option<[f32; 3]> {
    if !v.iter().all(|x| x.is_finite()) {
        return None;
    }
    let m = v[0].abs().max(v[1].abs()).max(v[2].abs());
    if m == 0.0 {
        return None;
    }
    let s = [v[0] / m, v[1] / m, v[2] / m];
    let len = norm(s);
    Some([s[0] / len, s[1] / len, s[2] / len])
}
