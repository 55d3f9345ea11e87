//! Vector-valued lattice noise for the perturbation of generator positions (§3.5): three independent value-noise
//! channels on an integer lattice, smoothly interpolated, each in [−1, 1]. The lattice values and the permutation
//! come from the instance seed's ChaCha8 stream, so perturbations are deterministic.

use crate::eval::unit_f32;
use crate::rng::{Context, InstanceRng};

/// Lattice size (a power of two).
const N: usize = 256;

/// A seeded 3D vector noise.
#[derive(Clone, Debug)]
pub struct VectorNoise {
    perm: [u8; N],
    values: Vec<[f32; 3]>,
}

impl VectorNoise {
    /// The noise of one instance: permutation and lattice vectors drawn from stream `key` of `rng`.
    pub fn new(rng: &mut InstanceRng, key: u64) -> VectorNoise {
        let mut ctx = Context { rng, key, counter: 0 };
        let mut perm: [u8; N] = std::array::from_fn(|i| i as u8);
        // Fisher–Yates with an explicit, unbiased-enough multiply-shift draw.
        for i in (1..N).rev() {
            let j = ((u64::from(crate::eval::Draw::next_u32(&mut ctx)) * (i as u64 + 1)) >> 32) as usize;
            perm.swap(i, j);
        }
        let values = (0..N)
            .map(|_| std::array::from_fn(|_| 2.0 * unit_f32(crate::eval::Draw::next_u32(&mut ctx)) - 1.0))
            .collect();
        VectorNoise { perm, values }
    }

    #[inline]
    fn lattice(&self, x: i32, y: i32, z: i32) -> &[f32; 3] {
        let p = &self.perm;
        let a = (i32::from(p[(x & 255) as usize]) + y) & 255;
        let b = (i32::from(p[a as usize]) + z) & 255;
        let h = p[b as usize];
        &self.values[h as usize]
    }

    /// The noise vector at `p`; every component lies in [−1, 1].
    pub fn sample(&self, p: [f32; 3]) -> [f32; 3] {
        let fl = p.map(libm::floorf);
        let f: [f32; 3] = std::array::from_fn(|i| p[i] - fl[i]);
        // Smoothstep fade: continuous first derivative across lattice cells.
        let w = f.map(|t| t * t * (3.0 - 2.0 * t));
        let c = fl.map(|v| v as i32);
        let mut out = [0.0f32; 3];
        for corner in 0..8 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
            let weight = (if dx == 1 { w[0] } else { 1.0 - w[0] })
                * (if dy == 1 { w[1] } else { 1.0 - w[1] })
                * (if dz == 1 { w[2] } else { 1.0 - w[2] });
            let v = self.lattice(c[0] + dx, c[1] + dy, c[2] + dz);
            for i in 0..3 {
                out[i] += weight * v[i];
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounded_continuous_and_seeded() {
        let mut rng = InstanceRng::new(5);
        let n = VectorNoise::new(&mut rng, 3);
        let mut prev = n.sample([0.0, 0.3, -0.7]);
        for i in 1..2000 {
            let p = [i as f32 * 0.001, 0.3, -0.7];
            let s = n.sample(p);
            assert!(s.iter().all(|v| (-1.0..=1.0).contains(v)));
            assert!(s.iter().zip(prev).all(|(a, b)| (a - b).abs() < 0.02), "continuous");
            prev = s;
        }
        let m = VectorNoise::new(&mut InstanceRng::new(6), 3);
        assert_ne!(n.sample([0.5, 0.5, 0.5]), m.sample([0.5, 0.5, 0.5]));
    }
}
