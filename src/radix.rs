//! Stable least-significant-digit radix sort by an integer key: the voxel filters of
//! [`crate::submap`] (a window's points) and [`crate::map`] (a map segment's voxels). Both
//! replaced hash tables whose probes missed the cache on every row; the sort's passes read and
//! write memory in order.

/// Bits per digit: 2,048 buckets, whose counters (16 KB) stay in L1.
const DIGIT_BITS: u32 = 11;

/// Sorts `rows` by `key(row)`, which must be below `2^bits`, keeping the order of rows with
/// equal keys; a pass whose digit is the same for every row is skipped. Every pass's counts come
/// from one read of the rows.
pub(crate) fn sort_by_key<T: Copy>(rows: &mut Vec<T>, bits: u32, key: impl Fn(&T) -> u64) {
    let buckets = 1usize << DIGIT_BITS;
    let digit = |row: &T, shift: u32| ((key(row) >> shift) as usize) & (buckets - 1);
    let passes = bits.min(u64::BITS).div_ceil(DIGIT_BITS) as usize;
    let mut counts = vec![0usize; passes * buckets];
    for row in rows.iter() {
        for (pass, slots) in counts.chunks_exact_mut(buckets).enumerate() {
            slots[digit(row, pass as u32 * DIGIT_BITS)] += 1;
        }
    }
    let mut scratch: Vec<T> = Vec::new();
    for (pass, offsets) in counts.chunks_exact_mut(buckets).enumerate() {
        if offsets.contains(&rows.len()) {
            continue;
        }
        let shift = pass as u32 * DIGIT_BITS;
        let mut start = 0;
        for slot in offsets.iter_mut() {
            let count = *slot;
            *slot = start;
            start += count;
        }
        if scratch.len() != rows.len() {
            scratch = rows.clone();
        }
        for row in rows.iter() {
            let d = digit(row, shift);
            scratch[offsets[d]] = *row;
            offsets[d] += 1;
        }
        std::mem::swap(rows, &mut scratch);
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
