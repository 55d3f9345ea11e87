//! f32 3-vector helpers for the hypertree generator and voxeliser, with a fixed operation order (component by
//! component, sums left to right, `libm::sqrtf`) so results are the same bits on every platform.

/// `a + b`.
#[inline]
pub fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|i| a[i] + b[i])
}

/// `a - b`.
#[inline]
pub fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|i| a[i] - b[i])
}

/// Euclidean length: `sqrtf(x·x + y·y + z·z)`, summed left to right.
#[inline]
pub fn norm(a: [f32; 3]) -> f32 {
    libm::sqrtf(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
}
