//! f32 3-vector helpers for the mesher, the hypertree generator, voxeliser and CPU raymarcher, with a fixed
//! operation order (component by component, sums left to right, `libm::sqrtf`) so results are the same bits on
//! every platform.

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
    libm::sqrtf(dot(a, a))
}

/// `a · b`, summed left to right.
#[inline]
pub fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`.
#[inline]
pub fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// `a / |a|` for rays and light directions; a zero vector is returned as it is.
#[inline]
pub fn unit(a: [f32; 3]) -> [f32; 3] {
    let n = norm(a);
    if n > 0.0 { a.map(|v| v / n) } else { a }
}

/// `v / |v|`, scaled by the largest component first so that huge or tiny vectors normalise too; `None` for a zero
/// or non-finite vector (the mesher's normals).
pub fn normalize(v: [f32; 3]) -> Option<[f32; 3]> {
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
