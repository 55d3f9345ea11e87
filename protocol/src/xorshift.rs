//! `XorShift64`: Marsaglia's 13/7/17 xorshift, a tiny deterministic generator for tests and mutation loops
//! (decoders fed mutated bytes, lanes delivered in a random order). Never for world content: amplification and
//! populations draw from ChaCha8 (`canopy_worlds::rng`), whose numbers are specified bit for bit.

/// A 64-bit xorshift generator (13, 7, 17). The state is never zero.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct XorShift64(u64);

impl XorShift64 {
    /// A generator from `seed`; a zero seed (which xorshift would never leave) becomes `0x2545_f491_4f6c_dd1d`.
    pub const fn new(seed: u64) -> XorShift64 {
        XorShift64(if seed == 0 { 0x2545_f491_4f6c_dd1d } else { seed })
    }

    /// The next value (the state after one step).
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }
}

#[cfg(test)]
mod tests {
    use super::XorShift64;

    #[test]
    fn known_sequence_and_no_zero_state() {
        let mut r = XorShift64::new(1);
        // 1 → 1 ^ 1<<13 = 0x2001; ^ >>7 = 0x2001 ^ 0x40 = 0x2041; ^ <<17 = 0x2041 ^ 0x4082_0000.
        assert_eq!(r.next(), 0x4082_2041);
        assert_eq!(XorShift64::new(0), XorShift64::new(0x2545_f491_4f6c_dd1d));
        let mut z = XorShift64::new(0);
        assert!((0..1000).all(|_| z.next() != 0));
    }
}
