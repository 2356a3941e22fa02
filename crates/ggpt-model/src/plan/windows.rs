//! Attention windows (network.md §7): the flash partition in sorted-position space (§7.2) and
//! the official padding tables `pad` / `unpad` / `cu_seqlens` (§7.3).

/// One attention window in sorted-position space (positions index an order row, `order[r][pos]`).
///
/// Tokens at positions `[start, start + len)` attend to each other; the outputs of positions
/// `[owned_from, owned_from + owned_len)` are taken from this window (each position is owned by
/// the first window that contains it, network.md §7.2). Windows never cross chunks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// First global sorted position of the window.
    pub start: usize,
    /// Number of positions in the window (`P`, or `n_b` for a short window).
    pub len: usize,
    /// First position whose output is taken from this window.
    pub owned_from: usize,
    /// Number of positions owned by this window.
    pub owned_len: usize,
}

/// Flash window partition (network.md §7.2) of a batch with per-chunk exclusive end `offsets`
/// (no leading zero) and patch size `patch` (`>= 1`): per chunk with `n` tokens, one short window
/// if `n <= P`, else windows `[wP, (w+1)P)` and a last window of the last `P` positions.
pub fn flash_windows(offsets: &[usize], patch: usize) -> Vec<Window> {
    let patch = patch.max(1);
    let mut out = Vec::new();
    let mut start = 0usize;
    for &end in offsets {
        let n = end.saturating_sub(start);
        if n == 0 {
            // Nothing to attend (never happens for planned chunks).
        } else if n <= patch {
            out.push(Window {
                start,
                len: n,
                owned_from: start,
                owned_len: n,
            });
        } else {
            let m = n.div_ceil(patch);
            for w in 0..m - 1 {
                let s = start + w * patch;
                out.push(Window {
                    start: s,
                    len: patch,
                    owned_from: s,
                    owned_len: patch,
                });
            }
            let owned_from = start + (m - 1) * patch;
            out.push(Window {
                start: end - patch,
                len: patch,
                owned_from,
                owned_len: end - owned_from,
            });
        }
        start = end.max(start);
    }
    out
}

/// The official padding tables of Pointcept's `get_padding_and_inverse` (network.md §7.3).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OfficialAttnTables {
    /// Padded slot -> global sorted position.
    pub pad: Vec<usize>,
    /// Global sorted position -> padded slot.
    pub unpad: Vec<usize>,
    /// Window boundaries in padded space, ending with the total padded length.
    pub cu_seqlens: Vec<usize>,
}

/// Builds the official `pad`, `unpad`, `cu_seqlens` tables (network.md §7.3) from per-chunk token
/// counts and the patch size `patch` (`>= 1`).
pub fn official_attn_tables(counts: &[usize], patch: usize) -> OfficialAttnTables {
    let p = patch.max(1);
    let padded: Vec<usize> = counts
        .iter()
        .map(|&n| if n > p { n.div_ceil(p) * p } else { n })
        .collect();
    let total: usize = counts.iter().sum();
    let total_pad: usize = padded.iter().sum();
    let mut pad: Vec<usize> = Vec::with_capacity(total_pad);
    let mut unpad: Vec<usize> = Vec::with_capacity(total);
    let mut cu = Vec::new();
    let (mut o, mut q) = (0usize, 0usize);
    for (&n, &np) in counts.iter().zip(&padded) {
        unpad.extend((o..o + n).map(|j| j + (q - o)));
        // Identity in padded space shifted back to sorted positions.
        let first = pad.len();
        pad.extend((q..q + np).map(|s| s - (q - o)));
        if n != np {
            // The last P - n mod P slots copy the entries P slots earlier.
            let r = n % p;
            let chunk_end = first + np;
            for s in (chunk_end - p + r)..chunk_end {
                let v = pad[s - p];
                pad[s] = v;
            }
        }
        cu.extend((q..q + np).step_by(p));
        o += n;
        q += np;
    }
    cu.push(q);
    OfficialAttnTables {
        pad,
        unpad,
        cu_seqlens: cu,
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    fn offsets(counts: &[usize]) -> Vec<usize> {
        counts
            .iter()
            .scan(0, |acc, &n| {
                *acc += n;
                Some(*acc)
            })
            .collect()
    }

    #[test]
    fn official_tables_test_vectors() {
        let t = official_attn_tables(&[5, 7], 4);
        assert_eq!(t.pad, [0, 1, 2, 3, 4, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 8]);
        assert_eq!(t.unpad, [0, 1, 2, 3, 4, 8, 9, 10, 11, 12, 13, 14]);
        assert_eq!(t.cu_seqlens, [0, 4, 8, 12, 16]);

        let t = official_attn_tables(&[3, 10], 4);
        assert_eq!(t.pad, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 9, 10]);
        assert_eq!(t.unpad, (0..13).collect::<Vec<_>>());
        assert_eq!(t.cu_seqlens, [0, 3, 7, 11, 15]);

        let t = official_attn_tables(&[10], 4);
        assert_eq!(t.pad, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 6, 7]);
        assert_eq!(t.unpad, (0..10).collect::<Vec<_>>());
        assert_eq!(t.cu_seqlens, [0, 4, 8, 12]);

        let t = official_attn_tables(&[9, 9, 2], 4);
        let pad: Vec<usize> = [
            vec![0, 1, 2, 3, 4, 5, 6, 7, 8, 5, 6, 7],
            vec![9, 10, 11, 12, 13, 14, 15, 16, 17, 14, 15, 16],
            vec![18, 19],
        ]
        .concat();
        assert_eq!(t.pad, pad);
        let unpad: Vec<usize> = (0..9).chain(12..21).chain(24..26).collect();
        assert_eq!(t.unpad, unpad);
        assert_eq!(t.cu_seqlens, [0, 4, 8, 12, 16, 20, 24, 26]);
    }

    /// The flash windows must describe exactly the same partition as the official padded tables:
    /// window `k` = the set of positions `pad[cu[k]..cu[k+1]]`, and ownership = first occurrence.
    #[test]
    fn flash_windows_equal_official_partition() {
        for (counts, p) in [
            (vec![5usize, 7], 4usize),
            (vec![3, 10], 4),
            (vec![10], 4),
            (vec![9, 9, 2], 4),
            (vec![679], 128),
            (vec![2296, 93, 128, 129, 256], 128),
            (vec![1, 1, 1], 1),
        ] {
            let wins = flash_windows(&offsets(&counts), p);
            let t = official_attn_tables(&counts, p);
            assert_eq!(wins.len() + 1, t.cu_seqlens.len());
            let mut owner = vec![usize::MAX; counts.iter().sum()];
            for (k, w) in wins.iter().enumerate() {
                let mut official: Vec<usize> = t.pad[t.cu_seqlens[k]..t.cu_seqlens[k + 1]].to_vec();
                official.sort_unstable();
                let mine: Vec<usize> = (w.start..w.start + w.len).collect();
                assert_eq!(official, mine, "counts {counts:?} window {k}");
                for pos in w.owned_from..w.owned_from + w.owned_len {
                    assert_eq!(owner[pos], usize::MAX, "position {pos} owned twice");
                    owner[pos] = k;
                }
                for pos in w.start..w.start + w.len {
                    assert!(
                        owner[pos] <= k,
                        "position {pos} not owned by its first window"
                    );
                }
            }
            assert!(owner.iter().all(|&o| o != usize::MAX));
        }
    }

    #[test]
    fn window_counts_of_the_fixture_levels() {
        for (n, m) in [
            (2296, 18),
            (1743, 14),
            (1109, 9),
            (753, 6),
            (531, 5),
            (679, 6),
            (592, 5),
            (371, 3),
            (163, 2),
            (93, 1),
        ] {
            assert_eq!(flash_windows(&[n], 128).len(), m, "n = {n}");
        }
        let w = flash_windows(&[679], 128);
        assert_eq!(
            w[5],
            Window {
                start: 551,
                len: 128,
                owned_from: 640,
                owned_len: 39
            }
        );
        assert_eq!(
            w[4],
            Window {
                start: 512,
                len: 128,
                owned_from: 512,
                owned_len: 128
            }
        );
        let w = flash_windows(&[93], 128);
        assert_eq!(
            w,
            [Window {
                start: 0,
                len: 93,
                owned_from: 0,
                owned_len: 93
            }]
        );
    }
}
