//! The LSD radix sorts behind validation (§5: sort, dedupe, count), for 32- and 64-bit keys.

/// LSD radix sort of 32-bit keys over their significant bits, in as few passes of at most 11 bits as they take.
pub fn radix_sort32(keys: &mut Vec<u32>, scratch: &mut Vec<u32>) {
    let n = keys.len();
    if n < 2 {
        return;
    }
    let all_or = keys.iter().fold(0u32, |a, &k| a | k);
    let bits = 32 - all_or.leading_zeros();
    if bits == 0 {
        return;
    }
    let passes = bits.div_ceil(11);
    let width = bits.div_ceil(passes);
    let buckets = 1usize << width;
    let mask = (buckets - 1) as u32;
    let mut counts = vec![0usize; buckets * passes as usize];
    for &k in keys.iter() {
        for p in 0..passes {
            counts[p as usize * buckets + ((k >> (p * width)) & mask) as usize] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, 0);
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
            let b = ((k >> shift) & mask) as usize;
            scratch[count[b]] = k;
            count[b] += 1;
        }
        std::mem::swap(keys, scratch);
    }
}

/// LSD radix sort of 64-bit keys by 11-bit digits, skipping digits that are equal in every key. The histograms of
/// all digits are counted in one pass over the keys.
pub fn radix_sort(keys: &mut Vec<u64>, scratch: &mut Vec<u64>) {
    const BITS: u32 = 11;
    const BUCKETS: usize = 1 << BITS;
    const DIGITS: usize = 64_usize.div_ceil(BITS as usize);
    let n = keys.len();
    if n < 2 {
        return;
    }
    let all_or = keys.iter().fold(0u64, |a, &k| a | k);
    let all_and = keys.iter().fold(u64::MAX, |a, &k| a & k);
    let varying = all_or ^ all_and;
    let digits: Vec<usize> =
        (0..DIGITS).filter(|&d| varying & (((BUCKETS as u64) - 1) << (d as u32 * BITS)) != 0).collect();
    let mut counts = vec![[0usize; BUCKETS]; digits.len()];
    for &k in keys.iter() {
        for (c, &d) in counts.iter_mut().zip(&digits) {
            c[((k >> (d as u32 * BITS)) as usize) & (BUCKETS - 1)] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, 0);
    for (count, &d) in counts.iter_mut().zip(&digits) {
        let shift = d as u32 * BITS;
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &k in keys.iter() {
            let b = ((k >> shift) as usize) & (BUCKETS - 1);
            scratch[count[b]] = k;
            count[b] += 1;
        }
        std::mem::swap(keys, scratch);
    }
}
