//! The plane curves of seed 002 §3.1 (Table 1): hypocycloids (deltoid, astroid, more cusps), ellipses, the
//! astroid as the envelope of co-axial generator ellipses with a constant sum of semi-axes, and roses
//! (rhodonea; the quadrifolium). Pure `f64` with `libm`, so every platform computes the same points.

use core::f64::consts::{FRAC_PI_2, PI, TAU};

/// A point of the hypocycloid with `cusps` cusps (3 deltoid, 4 astroid) and cusp radius 1, at rolling angle `t`:
/// `x = ((n − 1) cos t + cos((n − 1) t)) / n`, `y = ((n − 1) sin t − sin((n − 1) t)) / n`. The first cusp is on +x.
pub fn hypocycloid(cusps: u32, t: f64) -> [f64; 2] {
    let n = f64::from(cusps.max(3));
    let m = n - 1.0;
    [(m * libm::cos(t) + libm::cos(m * t)) / n, (m * libm::sin(t) - libm::sin(m * t)) / n]
}

/// The astroid `{cos³ t, sin³ t}` (the hypocycloid of four cusps).
pub fn astroid(t: f64) -> [f64; 2] {
    let (c, s) = (libm::cos(t), libm::sin(t));
    [c * c * c, s * s * s]
}

/// How far `(x, y)` is from the astroid: `|x|^(2/3) + |y|^(2/3) − 1` (zero on the curve).
pub fn astroid_residual(x: f64, y: f64) -> f64 {
    libm::pow(libm::fabs(x), 2.0 / 3.0) + libm::pow(libm::fabs(y), 2.0 / 3.0) - 1.0
}

/// How far `(x, y)` is from the deltoid of cusp radius 1 (cusp on +x), by its implicit equation with `a = 1/3`:
/// `(x² + y²)² + 18a²(x² + y²) − 27a⁴ − 8a(x³ − 3xy²)` (zero on the curve).
pub fn deltoid_residual(x: f64, y: f64) -> f64 {
    let a = 1.0 / 3.0;
    let r2 = x * x + y * y;
    r2 * r2 + 18.0 * a * a * r2 - 27.0 * a * a * a * a - 8.0 * a * (x * x * x - 3.0 * x * y * y)
}

/// The radius of the hypocycloid of `cusps` cusps (cusp radius 1) in the direction `theta`: hypocycloids are
/// star-shaped about their centre, so the ray meets the curve once. Found by bisection on the rolling angle
/// within one half-lobe (the curve has `n`-fold symmetry and is mirror-symmetric about each cusp).
pub fn hypocycloid_radius(cusps: u32, theta: f64) -> f64 {
    let n = cusps.max(3);
    let lobe = TAU / f64::from(n);
    let mut a = theta - libm::floor(theta / lobe) * lobe;
    if a > lobe / 2.0 {
        a = lobe - a;
    }
    // On t in [0, π/n] the polar angle rises monotonically from 0 (the cusp) to π/n (the waist).
    let (mut lo, mut hi) = (0.0f64, lobe / 2.0);
    for _ in 0..64 {
        let mid = 0.5 * (lo + hi);
        let p = hypocycloid(n, mid);
        if libm::atan2(p[1], p[0]) < a {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let p = hypocycloid(n, 0.5 * (lo + hi));
    libm::sqrt(p[0] * p[0] + p[1] * p[1])
}

/// The radius of the ellipse with semi-axes `a` (along x) and `b` (along y) in the direction `theta`:
/// `ab / √(b² cos² θ + a² sin² θ)`. A degenerate ellipse (`a` or `b` zero) is its segment.
pub fn ellipse_radius(a: f64, b: f64, theta: f64) -> f64 {
    let (c, s) = (libm::cos(theta), libm::sin(theta));
    let d = libm::sqrt(b * b * c * c + a * a * s * s);
    if d > 0.0 { a * b / d } else { a.max(b) }
}

/// The polar rose (rhodonea) `r = cos(k θ)`; `k = 2` is the quadrifolium.
pub fn rose(k: f64, theta: f64) -> f64 {
    libm::cos(k * theta)
}

/// A family of co-axial generator ellipses whose semi-axes sum to `sum` (seed 002 §3.1.2): ellipse `i` has
/// semi-axes `a = sum · cos² φᵢ` and `b = sum · sin² φᵢ`, touching the astroid of cusp radius `sum` at rolling
/// angle `φᵢ`. The angles are equi-spaced in `[φ₀, π/2 − φ₀]` with `cos 2φ₀ = width / sum`: the full family
/// (`width = sum`) envelops the astroid; narrower families round the cusps off, and `width = 0` leaves only the
/// circle of radius `sum / 2`.
#[derive(Clone, Debug, PartialEq)]
pub struct GeneratorEllipses {
    /// `(a, b)` of each ellipse, `a` along the lobe axis.
    pub axes: Vec<(f64, f64)>,
}

impl GeneratorEllipses {
    /// `count` ellipses (at least 1; one ellipse is the circle) with semi-axis sum `sum` and spread `width`.
    pub fn new(count: u32, sum: f64, width: f64) -> GeneratorEllipses {
        let count = count.max(1);
        let ratio = if sum > 0.0 { (width / sum).clamp(0.0, 1.0) } else { 0.0 };
        let phi0 = 0.5 * libm::acos(ratio);
        let axes = (0..count)
            .map(|i| {
                let phi = if count == 1 {
                    PI / 4.0
                } else {
                    phi0 + (FRAC_PI_2 - 2.0 * phi0) * f64::from(i) / f64::from(count - 1)
                };
                let (c, s) = (libm::cos(phi), libm::sin(phi));
                (sum * c * c, sum * s * s)
            })
            .collect();
        GeneratorEllipses { axes }
    }

    /// The radius of the envelope (the outer contour of the union) of the co-axial family in the direction
    /// `theta`: the largest of the ellipses' radii there.
    pub fn envelope_radius(&self, theta: f64) -> f64 {
        self.axes.iter().map(|&(a, b)| ellipse_radius(a, b, theta)).fold(0.0, f64::max)
    }

    /// The envelope with `lobes` lobes: for each lobe direction `ψₖ = 2πk / lobes` (turned by `phase[k]`), the
    /// forward halves of the ellipses elongated along it (`a ≥ b`, scaled towards the circle by `reach[k]`). For
    /// four lobes without perturbation this is exactly [`GeneratorEllipses::envelope_radius`]: an ellipse with
    /// `a < b` is one with `a > b` turned a quarter. Other lobe counts put astroid cusps at `2π / lobes`.
    pub fn lobed_radius(&self, lobes: u32, reach: &[f64], phase: &[f64], theta: f64) -> f64 {
        let n = lobes.max(3);
        let mut best = 0.0f64;
        for k in 0..n as usize {
            let psi = TAU * k as f64 / f64::from(n) + phase.get(k).copied().unwrap_or(0.0);
            let mut alpha = theta - psi;
            alpha -= libm::round(alpha / TAU) * TAU;
            if libm::fabs(alpha) > FRAC_PI_2 {
                continue;
            }
            let lambda = reach.get(k).copied().unwrap_or(1.0);
            for &(a, b) in &self.axes {
                if a + 1e-12 < b {
                    continue;
                }
                let a = b + (a - b) * lambda;
                best = best.max(ellipse_radius(a, b, alpha));
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn astroid_is_the_four_cusped_hypocycloid() {
        for i in 0..100 {
            let t = TAU * f64::from(i) / 100.0;
            let (h, a) = (hypocycloid(4, t), astroid(t));
            assert!((h[0] - a[0]).abs() < 1e-12 && (h[1] - a[1]).abs() < 1e-12);
            assert!(astroid_residual(a[0], a[1]).abs() < 1e-9);
        }
    }

    #[test]
    fn radius_function_inverts_the_parametrisation() {
        for n in 3..9 {
            for i in 0..50 {
                let t = TAU * f64::from(i) / 50.0 + 0.01;
                let p = hypocycloid(n, t);
                let r = hypocycloid_radius(n, libm::atan2(p[1], p[0]));
                assert!((r - libm::sqrt(p[0] * p[0] + p[1] * p[1])).abs() < 1e-9, "n {n} t {t}");
            }
        }
    }
}
