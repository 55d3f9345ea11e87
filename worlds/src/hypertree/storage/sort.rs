//! The LSD radix sort behind validation (§5: sort, dedupe, count), one implementation for 32- and 64-bit keys.

/// An unsigned integer key that [`radix_sort`] orders by its value. The sort works in the key's own width (widening
/// 32-bit keys to 64 bits made their sort measurably slower).
pub trait RadixKey: Copy + Default {
    /// The key's value, zero-extended to 64 bits.
    fn to_u64(self) -> u64;

    /// Bitwise or.
    fn or(self, other: Self) -> Self;

    /// The number of bits up to and including the highest set bit.
    fn significant_bits(self) -> u32;

    /// Bits `shift..` of the key, masked by `mask`: a digit.
    fn digit(self, shift: u32, mask: usize) -> usize;
}

macro_rules! radix_key {
    ($($t:ty),*) => {$(
        impl RadixKey for $t {
            #[inline(always)]
            fn to_u64(self) -> u64 {
                u64::from(self)
            }

            #[inline(always)]
            fn or(self, other: Self) -> Self {
                self | other
            }

            #[inline(always)]
            fn significant_bits(self) -> u32 {
                <$t>::BITS - self.leading_zeros()
            }

            #[inline(always)]
            fn digit(self, shift: u32, mask: usize) -> usize {
                (self >> shift) as usize & mask
            }
        }
    )*};
}

radix_key!(u32, u64);

/// Widest digit, in bits: 2 048 buckets of counts stay in the L1 cache.
const MAX_DIGIT_BITS: u32 = 11;

/// LSD radix sort of `keys` (`scratch` is working space, its contents are lost) over their significant bits (up to
/// the highest bit set in any key), in as few passes of at most [`MAX_DIGIT_BITS`] as they take, with digits of
/// equal width (fewer buckets than fixed 11-bit digits); a pass whose digit is the same in every key is skipped. The
/// histograms of all digits are counted in one pass over the keys.
pub fn radix_sort<K: RadixKey>(keys: &mut Vec<K>, scratch: &mut Vec<K>) {
    let n = keys.len();
    if n < 2 {
        return;
    }
    let bits = keys.iter().fold(K::default(), |a, &k| a.or(k)).significant_bits();
    if bits == 0 {
        return; // every key is 0
    }
    let passes = bits.div_ceil(MAX_DIGIT_BITS);
    let width = bits.div_ceil(passes);
    let buckets = 1usize << width;
    let mask = buckets - 1;
    let mut counts = vec![0usize; buckets * passes as usize];
    for &k in keys.iter() {
        for p in 0..passes {
            counts[p as usize * buckets + k.digit(p * width, mask)] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, K::default());
    for p in 0..passes {
        let count = &mut counts[p as usize * buckets..(p as usize + 1) * buckets];
        if count.contains(&n) {
            continue; // every key has the same digit here
        }
        let shift = p * width;
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &k in keys.iter() {
            let b = k.digit(shift, mask);
            scratch[count[b]] = k;
            count[b] += 1;
        }
        std::mem::swap(keys, scratch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic scramble of `i` (splitmix64's finaliser).
    fn mix(i: u64) -> u64 {
        let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn check<K: RadixKey + Ord + std::fmt::Debug>(mut keys: Vec<K>) {
        let mut want = keys.clone();
        want.sort_unstable();
        radix_sort(&mut keys, &mut Vec::new());
        assert_eq!(keys, want);
    }

    #[test]
    fn sorts_both_widths_whatever_bits_vary() {
        for n in [0usize, 1, 2, 3, 100, 5_000] {
            // Full-width keys, keys in a narrow band of middle bits, keys with a constant high part, all equal.
            check((0..n as u64).map(|i| mix(i) as u32).collect::<Vec<u32>>());
            check((0..n as u64).map(|i| (mix(i) as u32) >> 5 << 9 | 0x8000_0003).collect::<Vec<u32>>());
            check(vec![7u32; n]);
            check((0..n as u64).map(mix).collect::<Vec<u64>>());
            check((0..n as u64).map(|i| 3 << 40 | (mix(i) & 0x7ff_ffff) << 8 | mix(!i) & 31).collect::<Vec<u64>>());
            check((0..n as u64).map(|i| (mix(i) & 1) << 63 | 1 << 20).collect::<Vec<u64>>());
            check(vec![u64::MAX; n]);
        }
    }
}
