//! Deterministic mutations of a file's bytes: truncations, bit flips, byte edits, splices, and
//! oversized length / shape fields (ASCII numbers in headers and text formats, little-endian
//! words in binary ones).

use rand::{Rng, RngCore};

/// ASCII replacements for a run of digits (JSON headers, pickle text opcodes, PLY headers,
/// COLMAP text): limits of every integer width, negatives, floats where integers are expected.
const NUMBER_REPLACEMENTS: &[&str] = &[
    "0",
    "1",
    "-1",
    "2147483647",
    "2147483648",
    "4294967295",
    "4294967296",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999999999",
    "1e308",
    "-1e308",
    "1e400",
    "NaN",
    "inf",
    "3.5",
    "",
];

/// One mutation of a byte string.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Mutation {
    /// Keep the first `len` bytes.
    Truncate {
        /// Bytes kept.
        len: usize,
    },
    /// Flip one bit at each `(byte, bit)`.
    FlipBits {
        /// `(byte index, bit index)` pairs.
        bits: Vec<(usize, u8)>,
    },
    /// Overwrite one byte.
    SetByte {
        /// Byte index.
        at: usize,
        /// New value.
        value: u8,
    },
    /// Remove `len` bytes at `at`.
    Delete {
        /// First byte removed.
        at: usize,
        /// Bytes removed.
        len: usize,
    },
    /// Repeat the `len` bytes at `at` right after themselves.
    Duplicate {
        /// First byte repeated.
        at: usize,
        /// Bytes repeated.
        len: usize,
    },
    /// Insert bytes at `at`.
    Insert {
        /// Insertion index.
        at: usize,
        /// Bytes inserted.
        bytes: Vec<u8>,
    },
    /// Replace the ASCII digit run `start..end` by `with`.
    Number {
        /// First byte of the digit run.
        start: usize,
        /// One past the last byte of the digit run.
        end: usize,
        /// Replacement text.
        with: &'static str,
    },
    /// Overwrite `width` (4 or 8) bytes at `at` with `value`, little-endian.
    Word {
        /// Byte index.
        at: usize,
        /// Bytes overwritten (4 or 8).
        width: usize,
        /// Value written, little-endian.
        value: u64,
    },
}

impl Mutation {
    /// The mutated bytes.
    pub fn apply(&self, bytes: &[u8]) -> Vec<u8> {
        let mut out = bytes.to_vec();
        match self {
            Mutation::Truncate { len } => out.truncate(*len),
            Mutation::FlipBits { bits } => {
                for &(at, bit) in bits {
                    if let Some(b) = out.get_mut(at) {
                        *b ^= 1 << (bit % 8);
                    }
                }
            }
            Mutation::SetByte { at, value } => {
                if let Some(b) = out.get_mut(*at) {
                    *b = *value;
                }
            }
            Mutation::Delete { at, len } => {
                let a = (*at).min(out.len());
                let b = (a + len).min(out.len());
                out.drain(a..b);
            }
            Mutation::Duplicate { at, len } => {
                let a = (*at).min(out.len());
                let b = (a + len).min(out.len());
                let copy = out[a..b].to_vec();
                out.splice(b..b, copy);
            }
            Mutation::Insert { at, bytes } => {
                let a = (*at).min(out.len());
                out.splice(a..a, bytes.iter().copied());
            }
            Mutation::Number { start, end, with } => {
                let a = (*start).min(out.len());
                let b = (*end).clamp(a, out.len());
                out.splice(a..b, with.bytes());
            }
            Mutation::Word { at, width, value } => {
                let le = value.to_le_bytes();
                for (i, &b) in le.iter().take(*width).enumerate() {
                    if let Some(slot) = out.get_mut(at + i) {
                        *slot = b;
                    }
                }
            }
        }
        out
    }
}

/// Maximal runs of ASCII digits (start, end) in `bytes`.
pub fn digit_runs(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut runs = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit() {
            let s = i;
            while i < bytes.len() && bytes[i].is_ascii_digit() {
                i += 1;
            }
            runs.push((s, i));
        } else {
            i += 1;
        }
    }
    runs
}

/// Draws one mutation of `bytes` (non-empty or empty), with the digit runs of `bytes`
/// (`digit_runs`, precomputed by the caller because every case of a file shares them).
/// Structure-directed mutations (numbers, words, truncations) are drawn more often than plain
/// bit flips, which mostly land in payload data.
pub fn draw(rng: &mut impl RngCore, bytes: &[u8], runs: &[(usize, usize)]) -> Mutation {
    let n = bytes.len();
    let pos = |rng: &mut dyn RngCore| if n == 0 { 0 } else { rng.random_range(0..n) };
    // Positions near the start (headers) are drawn half of the time.
    let head_pos = |rng: &mut dyn RngCore| {
        if n == 0 {
            0
        } else if rng.random_bool(0.5) {
            rng.random_range(0..n.min(512))
        } else {
            rng.random_range(0..n)
        }
    };
    match rng.random_range(0..100) {
        0..15 => {
            let len = if n == 0 {
                0
            } else if rng.random_bool(0.5) {
                rng.random_range(0..n.min(256))
            } else {
                rng.random_range(0..n)
            };
            Mutation::Truncate { len }
        }
        15..35 => {
            let k = rng.random_range(1..=4);
            Mutation::FlipBits {
                bits: (0..k)
                    .map(|_| (head_pos(rng), rng.random_range(0..8)))
                    .collect(),
            }
        }
        35..43 => {
            let value = [0x00, 0xff, 0x7f, 0x80, b'"', b'{', b'\n', b' '][rng.random_range(0..8)];
            Mutation::SetByte {
                at: head_pos(rng),
                value,
            }
        }
        43..49 => Mutation::Delete {
            at: head_pos(rng),
            len: rng.random_range(1..=16),
        },
        49..54 => Mutation::Duplicate {
            at: head_pos(rng),
            len: rng.random_range(1..=64),
        },
        54..58 => {
            let len = rng.random_range(1..=8);
            Mutation::Insert {
                at: pos(rng),
                bytes: (0..len).map(|_| rng.random()).collect(),
            }
        }
        58..85 if !runs.is_empty() => {
            // numbers in the first 4 KiB (headers) are favoured
            let head: Vec<&(usize, usize)> = runs.iter().filter(|r| r.0 < 4096).collect();
            let &(start, end) = if !head.is_empty() && rng.random_bool(0.7) {
                head[rng.random_range(0..head.len())]
            } else {
                &runs[rng.random_range(0..runs.len())]
            };
            Mutation::Number {
                start,
                end,
                with: NUMBER_REPLACEMENTS[rng.random_range(0..NUMBER_REPLACEMENTS.len())],
            }
        }
        _ => {
            let width = if rng.random_bool(0.5) { 4 } else { 8 };
            let value = match rng.random_range(0..8) {
                0 => 0,
                1 => u64::from(u32::MAX),
                2 => u64::MAX,
                3 => 1 << 31,
                4 => 1 << 40,
                5 => n as u64,
                6 => n as u64 + 1,
                _ => rng.random(),
            };
            // aligned positions are where length and shape fields live
            let at = head_pos(rng) & !(width - 1);
            Mutation::Word { at, width, value }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn mutations_apply_as_described() {
        let b = b"ab12cd345".to_vec();
        assert_eq!(Mutation::Truncate { len: 3 }.apply(&b), b"ab1");
        assert_eq!(
            Mutation::FlipBits { bits: vec![(0, 0)] }.apply(&b)[0],
            b'a' ^ 1
        );
        assert_eq!(Mutation::Delete { at: 2, len: 2 }.apply(&b), b"abcd345");
        assert_eq!(
            Mutation::Duplicate { at: 0, len: 2 }.apply(&b),
            b"abab12cd345"
        );
        assert_eq!(
            Mutation::Number {
                start: 2,
                end: 4,
                with: "4294967296"
            }
            .apply(&b),
            b"ab4294967296cd345"
        );
        assert_eq!(
            Mutation::Word {
                at: 0,
                width: 4,
                value: 1
            }
            .apply(&b)[..4],
            [1, 0, 0, 0]
        );
        assert_eq!(digit_runs(&b), vec![(2, 4), (6, 9)]);
        // out-of-range positions never panic
        assert_eq!(Mutation::Delete { at: 100, len: 5 }.apply(&b), b);
        assert_eq!(
            Mutation::Word {
                at: 7,
                width: 8,
                value: u64::MAX
            }
            .apply(&b)
            .len(),
            b.len()
        );
    }

    #[test]
    fn draws_are_deterministic_and_varied() {
        let b: Vec<u8> = (0..2000u32).map(|i| (i % 251) as u8).collect();
        let runs = digit_runs(&b);
        let mut r1 = rand_pcg::Pcg64::seed_from_u64(7);
        let mut r2 = rand_pcg::Pcg64::seed_from_u64(7);
        let a: Vec<Mutation> = (0..200).map(|_| draw(&mut r1, &b, &runs)).collect();
        let c: Vec<Mutation> = (0..200).map(|_| draw(&mut r2, &b, &runs)).collect();
        assert_eq!(a, c);
        let kinds: std::collections::BTreeSet<_> = a
            .iter()
            .map(std::mem::discriminant)
            .map(|d| format!("{d:?}"))
            .collect();
        assert!(
            kinds.len() >= 7,
            "only {} mutation kinds in 200 draws",
            kinds.len()
        );
    }
}
