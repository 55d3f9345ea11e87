//! Affine transforms for traversal: a 3×4 row-major matrix with an explicit, platform-independent operation order
//! (no SIMD, no fused multiply-add), so every platform computes bit-identical world transforms.

/// An affine transform: rows `[r0 | t0], [r1 | t1], [r2 | t2]` of a 3×4 matrix, row-major.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// The twelve entries, row-major: `m[4 * row + col]`, column 3 is the translation.
    pub m: [f32; 12],
}

impl Default for Transform {
    fn default() -> Self {
        Transform::IDENTITY
    }
}

impl Transform {
    /// The identity.
    pub const IDENTITY: Transform = Transform { m: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0] };

    /// A translation.
    pub fn translation(x: f32, y: f32, z: f32) -> Transform {
        Transform { m: [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, y, 0.0, 0.0, 1.0, z] }
    }

    /// A scale.
    pub fn scale(x: f32, y: f32, z: f32) -> Transform {
        Transform { m: [x, 0.0, 0.0, 0.0, 0.0, y, 0.0, 0.0, 0.0, 0.0, z, 0.0] }
    }

    /// A rotation of `degrees` about `axis` (normalised here; a zero axis gives the identity), right-handed.
    pub fn rotation(axis: [f32; 3], degrees: f32) -> Transform {
        let len = libm::sqrtf(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
        if len.is_nan() || len <= 0.0 || !len.is_finite() {
            return Transform::IDENTITY;
        }
        let (x, y, z) = (axis[0] / len, axis[1] / len, axis[2] / len);
        let rad = degrees * (core::f32::consts::PI / 180.0);
        let (s, c) = (libm::sinf(rad), libm::cosf(rad));
        let t = 1.0 - c;
        Transform {
            m: [
                t * x * x + c,
                t * x * y - s * z,
                t * x * z + s * y,
                0.0,
                t * x * y + s * z,
                t * y * y + c,
                t * y * z - s * x,
                0.0,
                t * x * z - s * y,
                t * y * z + s * x,
                t * z * z + c,
                0.0,
            ],
        }
    }

    /// `self · other`: apply `other` first, then `self` (post-multiplication, as traversal accumulates).
    #[inline]
    pub fn mul(&self, o: &Transform) -> Transform {
        let a = &self.m;
        let b = &o.m;
        let mut m = [0.0f32; 12];
        for r in 0..3 {
            let (a0, a1, a2, a3) = (a[4 * r], a[4 * r + 1], a[4 * r + 2], a[4 * r + 3]);
            for c in 0..3 {
                m[4 * r + c] = a0 * b[c] + a1 * b[4 + c] + a2 * b[8 + c];
            }
            m[4 * r + 3] = a0 * b[3] + a1 * b[7] + a2 * b[11] + a3;
        }
        Transform { m }
    }

    /// `self · translation(x, y, z)`, without the full product.
    #[inline]
    pub fn translated(&self, x: f32, y: f32, z: f32) -> Transform {
        let mut t = *self;
        for r in 0..3 {
            let a = &self.m[4 * r..4 * r + 4];
            t.m[4 * r + 3] = a[0] * x + a[1] * y + a[2] * z + a[3];
        }
        t
    }

    /// Transform a point.
    #[inline]
    pub fn point(&self, p: [f32; 3]) -> [f32; 3] {
        let m = &self.m;
        [
            m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3],
            m[4] * p[0] + m[5] * p[1] + m[6] * p[2] + m[7],
            m[8] * p[0] + m[9] * p[1] + m[10] * p[2] + m[11],
        ]
    }

    /// Transform a direction (no translation).
    #[inline]
    pub fn vector(&self, v: [f32; 3]) -> [f32; 3] {
        let m = &self.m;
        [
            m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
            m[4] * v[0] + m[5] * v[1] + m[6] * v[2],
            m[8] * v[0] + m[9] * v[1] + m[10] * v[2],
        ]
    }

    /// The cofactor matrix of the linear part (rows), which maps normals correctly under any invertible
    /// transform up to a positive scale (normalise afterwards); for a mirroring transform it flips them, which
    /// [`Transform::determinant`] tells.
    pub fn normal_matrix(&self) -> [[f32; 3]; 3] {
        let m = &self.m;
        let (a, b, c, d, e, f, g, h, i) = (m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
        [
            [e * i - f * h, f * g - d * i, d * h - e * g],
            [c * h - b * i, a * i - c * g, b * g - a * h],
            [b * f - c * e, c * d - a * f, a * e - b * d],
        ]
    }

    /// Determinant of the linear part.
    pub fn determinant(&self) -> f32 {
        let m = &self.m;
        m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) + m[2] * (m[4] * m[9] - m[5] * m[8])
    }

    /// The scale factor along local axis `c` (0, 1 or 2): the length of column `c` of the linear part.
    pub fn axis_scale(&self, c: usize) -> f32 {
        let m = &self.m;
        libm::sqrtf(m[c] * m[c] + m[4 + c] * m[4 + c] + m[8 + c] * m[8 + c])
    }

    /// The largest scale factor along the local axes (length of the longest column), for size estimates.
    pub fn max_axis_scale(&self) -> f32 {
        libm::fmaxf(libm::fmaxf(self.axis_scale(0), self.axis_scale(1)), self.axis_scale(2))
    }

    /// The inverse transform, or `None` if the linear part is singular (|determinant| ≤ 1e-20) or not finite.
    pub fn inverse(&self) -> Option<Transform> {
        let det = self.determinant();
        if !det.is_finite() || det.abs() <= 1e-20 {
            return None;
        }
        let c = self.normal_matrix();
        let mut m = [0.0f32; 12];
        for r in 0..3 {
            for k in 0..3 {
                m[4 * r + k] = c[k][r] / det;
            }
        }
        let tr = [self.m[3], self.m[7], self.m[11]];
        for r in 0..3 {
            m[4 * r + 3] = -(m[4 * r] * tr[0] + m[4 * r + 1] * tr[1] + m[4 * r + 2] * tr[2]);
        }
        Some(Transform { m })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: [f32; 3], b: [f32; 3]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6)
    }

    #[test]
    fn rotation_is_right_handed_in_degrees() {
        let r = Transform::rotation([0.0, 0.0, 1.0], 90.0);
        assert!(close(r.vector([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]));
        let r = Transform::rotation([1.0, 0.0, 0.0], 90.0);
        assert!(close(r.vector([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]));
    }

    #[test]
    fn post_multiplication_applies_the_later_transform_first() {
        let t = Transform::translation(1.0, 0.0, 0.0).mul(&Transform::rotation([0.0, 0.0, 1.0], 90.0));
        assert!(close(t.point([1.0, 0.0, 0.0]), [1.0, 1.0, 0.0]));
        let a = Transform::rotation([0.3, 1.0, 0.2], 33.0);
        assert_eq!(a.translated(1.0, 2.0, 3.0), a.mul(&Transform::translation(1.0, 2.0, 3.0)));
    }

    #[test]
    fn normal_matrix_keeps_normals_perpendicular() {
        let t = Transform::scale(1.0, 4.0, 1.0).mul(&Transform::rotation([0.0, 0.0, 1.0], 30.0));
        let n = t.normal_matrix();
        // A surface spanned by x and z has normal y; after the transform it must stay perpendicular.
        let nt = [n[0][1], n[1][1], n[2][1]];
        let (u, v) = (t.vector([1.0, 0.0, 0.0]), t.vector([0.0, 0.0, 1.0]));
        let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        assert!(dot(nt, u).abs() < 1e-5 && dot(nt, v).abs() < 1e-5);
    }
}
