//! The instance RNG: ChaCha8 keyed by the instance seed, read as counter-addressed streams so that every random
//! draw depends on where in the derivation it happens, never on traversal order.
//!
//! A draw is word `counter` of ChaCha8 stream `key`. Traversal starts in context `(ROOT_KEY, 0)`; each
//! [`canopy_protocol::Node::RecursionSeparator`] entered at parent context `(key, c)` opens the child context
//! `(child_key(key, c), 0)` and advances the parent to `(key, c + 1)`. The L-system string-rewriting reference
//! gives each non-terminal module occurrence its context by the same rule, which is why the graph derivation and
//! string rewriting agree draw for draw — and why lowering the recursion depth for LOD does not reshuffle the rest
//! of the tree.

use crate::eval::{Draw, unit_f32};

/// The context key at the root of a traversal.
pub const ROOT_KEY: u64 = 0;

/// SplitMix64's finaliser: a bijective 64-bit mix.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The key of the context opened by the `counter`-th call made from context `key`.
#[inline]
pub fn child_key(key: u64, counter: u64) -> u64 {
    mix64(key ^ mix64(counter.wrapping_add(0x9e37_79b9_7f4a_7c15)))
}

/// The 32-byte ChaCha key of an instance seed (SplitMix64 expansion, little-endian).
pub fn seed_bytes(seed: u64) -> [u8; 32] {
    let mut out = [0u8; 32];
    let mut s = seed;
    for chunk in out.chunks_exact_mut(8) {
        s = s.wrapping_add(0x9e37_79b9_7f4a_7c15);
        chunk.copy_from_slice(&mix64(s).to_le_bytes());
    }
    out
}

/// One ChaCha8 block (DJB layout: constants, 256-bit key, 64-bit block counter, 64-bit stream), the same
/// function `rand_chacha::ChaCha8Rng` computes (a test holds the two together). Computed one block at a time so a
/// context costs one block, not the four `ChaCha8Rng` refills at every seek.
pub fn chacha8_block(key: &[u32; 8], stream: u64, block: u64) -> [u32; 16] {
    let mut s = [0u32; 16];
    s[..4].copy_from_slice(&[0x6170_7865, 0x3320_646e, 0x7962_2d32, 0x6b20_6574]);
    s[4..12].copy_from_slice(key);
    s[12] = block as u32;
    s[13] = (block >> 32) as u32;
    s[14] = stream as u32;
    s[15] = (stream >> 32) as u32;
    let mut x = s;
    #[inline(always)]
    fn qr(x: &mut [u32; 16], a: usize, b: usize, c: usize, d: usize) {
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(16);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(12);
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(8);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(7);
    }
    for _ in 0..4 {
        qr(&mut x, 0, 4, 8, 12);
        qr(&mut x, 1, 5, 9, 13);
        qr(&mut x, 2, 6, 10, 14);
        qr(&mut x, 3, 7, 11, 15);
        qr(&mut x, 0, 5, 10, 15);
        qr(&mut x, 1, 6, 11, 12);
        qr(&mut x, 2, 7, 8, 13);
        qr(&mut x, 3, 4, 9, 14);
    }
    for (o, i) in x.iter_mut().zip(s) {
        *o = o.wrapping_add(i);
    }
    x
}

/// The most recently computed block of one stream: what a context keeps so consecutive draws cost nothing.
#[derive(Clone, Copy, Debug)]
pub struct BlockCache {
    stream: u64,
    block: u64,
    words: [u32; 16],
    valid: bool,
}

impl BlockCache {
    /// An empty cache.
    pub const EMPTY: BlockCache = BlockCache { stream: 0, block: 0, words: [0; 16], valid: false };
}

/// ChaCha8 for one instance, addressed by (stream, word).
#[derive(Clone, Debug)]
pub struct InstanceRng {
    key: [u32; 8],
    /// The block last used; traversal saves and restores it around recursion separators.
    pub cache: BlockCache,
}

impl InstanceRng {
    /// The RNG of the instance with this seed.
    pub fn new(seed: u64) -> InstanceRng {
        let bytes = seed_bytes(seed);
        let key = std::array::from_fn(|i| u32::from_le_bytes(bytes[4 * i..4 * i + 4].try_into().expect("4 bytes")));
        InstanceRng { key, cache: BlockCache::EMPTY }
    }

    /// Word `index` of stream `stream`.
    #[inline]
    pub fn word(&mut self, stream: u64, index: u64) -> u32 {
        let block = index >> 4;
        let c = &mut self.cache;
        if !(c.valid && c.stream == stream && c.block == block) {
            *c = BlockCache { stream, block, words: chacha8_block(&self.key, stream, block), valid: true };
        }
        c.words[(index & 15) as usize]
    }

    /// Position-keyed noise in [0, 1): word 0 of a stream named by the bits of `x` and `y`. It does not disturb
    /// the block cache of the current context.
    pub fn noise(&mut self, x: f32, y: f32) -> f32 {
        let stream = mix64(u64::from(x.to_bits()) << 32 | u64::from(y.to_bits()) ^ 0x6e6f_6973_6500_0000);
        unit_f32(chacha8_block(&self.key, stream, 0)[0])
    }
}

/// A draw context: the instance RNG at `(key, counter)`; each draw advances the counter.
pub struct Context<'r> {
    /// The instance RNG.
    pub rng: &'r mut InstanceRng,
    /// The context key.
    pub key: u64,
    /// The next word to draw.
    pub counter: u64,
}

impl Draw for Context<'_> {
    #[inline]
    fn next_u32(&mut self) -> u32 {
        let w = self.rng.word(self.key, self.counter);
        self.counter += 1;
        w
    }
    fn noise(&mut self, x: f32, y: f32) -> f32 {
        self.rng.noise(x, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_words() {
        // Pinned output: any change to seeding or addressing changes every tree in every world.
        let mut r = InstanceRng::new(42);
        let w = [r.word(ROOT_KEY, 0), r.word(ROOT_KEY, 1), r.word(7, 0), r.word(ROOT_KEY, 1)];
        assert_eq!(w[1], w[3], "addressing is random access");
        assert_eq!(w, [GOLDEN[0], GOLDEN[1], GOLDEN[2], GOLDEN[1]]);
        assert_eq!(child_key(ROOT_KEY, 0), GOLDEN_KEY);
    }

    const GOLDEN: [u32; 3] = [2_278_103_804, 823_500_537, 2_290_579_414];
    const GOLDEN_KEY: u64 = 5_197_578_548_964_807_871;

    #[test]
    fn block_function_is_rand_chachas_chacha8() {
        use rand_chacha::ChaCha8Rng;
        use rand_core::{Rng, SeedableRng};
        for (seed, stream, start) in [(0u64, 0u64, 0u64), (42, 7, 16), (u64::MAX, u64::MAX - 3, 1 << 40)] {
            let mut oracle = ChaCha8Rng::from_seed(seed_bytes(seed));
            oracle.set_stream(stream);
            oracle.set_word_pos(u128::from(start));
            let mut ours = InstanceRng::new(seed);
            for i in 0..64 {
                assert_eq!(
                    ours.word(stream, start + i),
                    oracle.next_u32(),
                    "seed {seed} stream {stream} word {}",
                    start + i
                );
            }
        }
    }

    #[test]
    fn sequential_and_random_access_agree() {
        let mut a = InstanceRng::new(9);
        let seq: Vec<u32> = (0..40).map(|i| a.word(5, i)).collect();
        let mut b = InstanceRng::new(9);
        for i in (0..40).rev() {
            assert_eq!(b.word(5, i), seq[i as usize]);
        }
    }
}
