//! The LSD radix sort behind validation (§5: sort, dedupe, count), one implementation for 32- and 64-bit keys.

/// An unsigned integer key that [`radix_sort`] orders by its value.
pub trait RadixKey: Copy + Default {
    /// The key's value, zero-extended to 64 bits.
    fn to_u64(self) -> u64;
}

impl RadixKey for u32 {
    #[inline(always)]
    fn to_u64(self) -> u64 {
        u64::from(self)
    }
}

impl RadixKey for u64 {
    #[inline(always)]
    fn to_u64(self) -> u64 {
        self
    }
}

/// Widest digit, in bits: 2 048 buckets of counts stay in the L1 cache.
const MAX_DIGIT_BITS: u32 = 11;

/// LSD radix sort of `keys` (`scratch` is working space, its contents are lost). Only the span of bits that differ
/// between keys is sorted, in as few passes of at most [`MAX_DIGIT_BITS`] as it takes, with the span split into
/// digits of equal width (fewer buckets than fixed 11-bit digits); a pass whose digit is the same in every key is
/// skipped. The histograms of all digits are counted in one pass over the keys.
pub fn radix_sort<K: RadixKey>(keys: &mut Vec<K>, scratch: &mut Vec<K>) {
    let n = keys.len();
    if n < 2 {
        return;
    }
    let (all_or, all_and) = keys.iter().fold((0u64, u64::MAX), |(o, a), &k| (o | k.to_u64(), a & k.to_u64()));
    let varying = all_or ^ all_and;
    if varying == 0 {
        return; // every key is equal
    }
    let low = varying.trailing_zeros();
    let bits = u64::BITS - varying.leading_zeros() - low;
    let passes = bits.div_ceil(MAX_DIGIT_BITS) as usize;
    let width = bits.div_ceil(passes as u32);
    let buckets = 1usize << width;
    let mask = (buckets - 1) as u64;
    // Digit `p` is bits `low + p · width ..` of a key; the last one ends at or below bit 63 (`(passes − 1)² < bits`).
    let shift = |p: usize| low + p as u32 * width;
    let mut counts = vec![0usize; buckets * passes];
    for &k in keys.iter() {
        let k = k.to_u64();
        for p in 0..passes {
            counts[p * buckets + ((k >> shift(p)) & mask) as usize] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, K::default());
    for p in 0..passes {
        let count = &mut counts[p * buckets..(p + 1) * buckets];
        if count.contains(&n) {
            continue; // every key has the same digit here
        }
        let s = shift(p);
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &k in keys.iter() {
            let b = ((k.to_u64() >> s) & mask) as usize;
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
