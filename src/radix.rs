//! Stable radix sort by an integer key (least-significant digit first; large inputs split by
//! their most significant digit first): the voxel filters of [`crate::submap`] (a window's
//! points) and [`crate::map`] (a map segment's voxels). Both replaced hash tables whose probes
//! missed the cache on every row; the sort's passes read and write memory in order.

/// Bits per digit: 2,048 buckets, whose counters (16 KB) stay in L1.
const DIGIT_BITS: u32 = 11;

/// From this many rows on (a 64-beam window: ~1.2 M rows, 19 MB, more than the L2 and with
/// its scratch more than the L3 of our 2-core machines), the rows are first split by their
/// highest digit and each bucket is then sorted on its own, in cache: one pass over the
/// whole array instead of one per digit.
const SPLIT_MIN_ROWS: usize = 1 << 16;

/// Sorts `rows` by `key(row)`, which must be below `2^bits`, keeping the order of rows with
/// equal keys; a pass whose digit is the same for every row is skipped. Every pass's counts come
/// from one read of the rows. Large inputs are split by their highest digit first
/// ([`SPLIT_MIN_ROWS`]); the order is the same either way (both are stable sorts by the key).
pub(crate) fn sort_by_key<T: Copy>(rows: &mut Vec<T>, bits: u32, key: impl Fn(&T) -> u64) {
    let bits = bits.min(u64::BITS);
    let mut scratch = Scratch {
        rows: Vec::new(),
        counts: Vec::new(),
    };
    if rows.len() < SPLIT_MIN_ROWS || bits <= 2 * DIGIT_BITS {
        sort_slice(rows, &mut scratch, bits, &key);
        return;
    }
    // Split by the highest digit into `split` (stable), then sort each bucket by the rest.
    let shift = bits - DIGIT_BITS;
    let top = |row: &T| (key(row) >> shift) as usize & ((1 << DIGIT_BITS) - 1);
    let mut counts = vec![0usize; 1 << DIGIT_BITS];
    for row in rows.iter() {
        counts[top(row)] += 1;
    }
    to_offsets(&mut counts);
    let starts = counts.clone();
    let mut split = rows.clone();
    for row in rows.iter() {
        let d = top(row);
        split[counts[d]] = *row;
        counts[d] += 1;
    }
    // Each bucket's end is now where the scatter stopped.
    for (&start, &end) in starts.iter().zip(&counts) {
        sort_slice(&mut split[start..end], &mut scratch, shift, &key);
    }
    *rows = split;
}

/// Bucket counts into the bucket's first slots (exclusive prefix sums), in place.
fn to_offsets(slots: &mut [usize]) {
    let mut start = 0;
    for slot in slots.iter_mut() {
        let count = *slot;
        *slot = start;
        start += count;
    }
}

/// Buffers reused by the buckets of one sort.
struct Scratch<T> {
    rows: Vec<T>,
    counts: Vec<usize>,
}

/// Below this many rows a bucket is sorted by insertion (stable), not by digits.
const INSERTION_MAX_ROWS: usize = 32;

/// Least-significant digit first over the low `bits` bits of the key (a handful of rows: by
/// insertion), with reused buffers; the sorted rows end up in `rows`.
fn sort_slice<T: Copy>(
    rows: &mut [T],
    scratch: &mut Scratch<T>,
    bits: u32,
    key: &impl Fn(&T) -> u64,
) {
    if rows.len() <= INSERTION_MAX_ROWS {
        for i in 1..rows.len() {
            let row = rows[i];
            let k = key(&row);
            let mut j = i;
            while j > 0 && key(&rows[j - 1]) > k {
                rows[j] = rows[j - 1];
                j -= 1;
            }
            rows[j] = row;
        }
        return;
    }
    let buckets = 1usize << DIGIT_BITS;
    let digit = |row: &T, shift: u32| ((key(row) >> shift) as usize) & (buckets - 1);
    let passes = bits.div_ceil(DIGIT_BITS) as usize;
    let counts = &mut scratch.counts;
    counts.clear();
    counts.resize(passes * buckets, 0);
    for row in rows.iter() {
        for (pass, slots) in counts.chunks_exact_mut(buckets).enumerate() {
            slots[digit(row, pass as u32 * DIGIT_BITS)] += 1;
        }
    }
    let scratch = &mut scratch.rows;
    scratch.clear(); // filled by the first pass that moves rows
    // Where the rows are between passes: `rows` or `scratch`.
    let mut in_scratch = false;
    for (pass, offsets) in counts.chunks_exact_mut(buckets).enumerate() {
        if offsets.contains(&rows.len()) {
            continue;
        }
        let shift = pass as u32 * DIGIT_BITS;
        to_offsets(offsets);
        if scratch.is_empty() {
            scratch.extend_from_slice(rows);
        }
        let (src, dst): (&[T], &mut [T]) = if in_scratch {
            (&scratch[..], &mut rows[..])
        } else {
            (&rows[..], &mut scratch[..])
        };
        for row in src.iter() {
            let d = digit(row, shift);
            dst[offsets[d]] = *row;
            offsets[d] += 1;
        }
        in_scratch = !in_scratch;
    }
    if in_scratch {
        rows.copy_from_slice(scratch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sorts_like_a_stable_sort_on_the_low_bits() {
        // A small linear congruential generator: keys over several digits, many repeats.
        let mut state = 12345u64;
        let mut rows: Vec<(u64, usize)> = (0..5000)
            .map(|i| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 20) & 0x3FF_FFFF, i)
            })
            .collect();
        let mut expected = rows.clone();
        expected.sort_by_key(|r| r.0);
        sort_by_key(&mut rows, 26, |r| r.0);
        assert_eq!(rows, expected);
    }

    #[test]
    fn large_inputs_split_by_the_highest_digit_sort_the_same() {
        // Above SPLIT_MIN_ROWS: 30-bit keys (a 64-beam window's), 40 bits, and keys whose
        // highest digit is constant (one bucket) or only in the top bits.
        for (bits, mask) in [
            (30u32, 0x3FFF_FFFFu64),
            (40, 0xFF_FFFF_FFFF),
            (30, 0xF_FFFF),
        ] {
            let mut state = 99u64;
            let mut rows: Vec<(u64, usize)> = (0..SPLIT_MIN_ROWS + 12_345)
                .map(|i| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    // Few distinct keys per bucket as well as many: equal keys keep their order.
                    let k = (state >> 17) & mask;
                    (if i % 3 == 0 { k & !0xFF } else { k }, i)
                })
                .collect();
            let mut expected = rows.clone();
            expected.sort_by_key(|r| r.0);
            sort_by_key(&mut rows, bits, |r| r.0);
            assert_eq!(rows, expected, "{bits} bits");
        }
        let mut top_only: Vec<(u64, usize)> = (0..SPLIT_MIN_ROWS)
            .map(|i| ((((i * 7919) % 2048) as u64) << 29, i))
            .collect();
        let mut expected = top_only.clone();
        expected.sort_by_key(|r| r.0);
        sort_by_key(&mut top_only, 40, |r| r.0);
        assert_eq!(top_only, expected);
    }

    #[test]
    fn a_constant_digit_is_skipped_and_empty_input_is_fine() {
        let mut rows = vec![
            (7u64 << 22 | 3, 0),
            (7u64 << 22 | 1, 1),
            (7u64 << 22 | 3, 2),
        ];
        sort_by_key(&mut rows, 33, |r| r.0);
        assert_eq!(rows.iter().map(|r| r.1).collect::<Vec<_>>(), vec![1, 0, 2]);
        let mut empty: Vec<(u64, u8)> = Vec::new();
        sort_by_key(&mut empty, 64, |r| r.0);
        assert!(empty.is_empty());
    }
}
