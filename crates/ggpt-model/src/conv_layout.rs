//! The neighbour tables of one level's submanifold convolution (network.md §6) as one packed
//! index list and the layout that reads it: what the conv op of the kernel layer
//! ([`crate::kernels::subm_conv`]) takes, built once per level by [`crate::prepared`].
//!
//! ```text
//! packed = [ im2col        [N · 27]   row of X_ext = [x; group sums; 0] feeding tap f of token t
//!                                      at t · 27 + f (N + G: the zero row, "no neighbour")
//!          | members       [M]        member token of each group entry      (G > 0 only)
//!          | ids           [M]        group of each group entry              (G > 0 only)
//!          | source_f, target_f  [P_f] each, per occupied tap f in `taps` order ]
//! ```

/// Number of kernel taps (3x3x3).
pub const NUM_TAPS: usize = 27;

/// One occupied kernel tap of a [`ConvLayout`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvTap {
    /// Tap `f` (`W_f = weight[:, f / 9, (f / 3) % 3, f % 3, :]`).
    pub tap: usize,
    /// Pairs `P_f` (tokens with this neighbour).
    pub len: usize,
    /// Every token has this neighbour (`target == 0..N`): the scatter is a plain add.
    pub full: bool,
    /// `full` and `source == 0..N` (the centre tap without duplicates): no gather either.
    pub identity: bool,
}

/// Where each table sits in the packed list (module docs), and what the op needs besides.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvLayout {
    /// Tokens `N`.
    pub num_tokens: usize,
    /// Summed groups `G` (rows `N .. N + G` of `X_ext`).
    pub num_groups: usize,
    /// Group entries `M` (0 when `G = 0`).
    pub num_group_entries: usize,
    /// The taps with at least one pair, in packed order.
    pub taps: Vec<ConvTap>,
    /// Occupied slots / `27 N` (1 = every token has all 27 neighbours).
    pub occupancy: f64,
}

/// `(offset, length)` of one table in the packed list.
pub type Span = (usize, usize);

impl ConvLayout {
    /// The im2col table `[N · 27]`.
    pub fn im2col(&self) -> Span {
        (0, self.num_tokens * NUM_TAPS)
    }

    /// The group members and ids `[M]` each; `None` when there are no groups.
    pub fn groups(&self) -> Option<(Span, Span)> {
        let m = self.num_group_entries;
        let start = self.num_tokens * NUM_TAPS;
        (self.num_groups > 0 && m > 0).then_some(((start, m), (start + m, m)))
    }

    /// The source and target tables of every tap, in `taps` order.
    pub fn tap_spans(&self) -> Vec<(Span, Span)> {
        let mut offset = self.num_tokens * NUM_TAPS + 2 * self.num_group_entries;
        self.taps
            .iter()
            .map(|t| {
                let spans = ((offset, t.len), (offset + t.len, t.len));
                offset += 2 * t.len;
                spans
            })
            .collect()
    }

    /// Entries of the packed list.
    pub fn packed_len(&self) -> usize {
        self.num_tokens * NUM_TAPS
            + 2 * self.num_group_entries
            + 2 * self.taps.iter().map(|t| t.len).sum::<usize>()
    }
}

/// The packed list and its layout from the im2col table of `n` tokens (entries in
/// `0..=n + num_groups`, `n + num_groups` meaning "no neighbour") and the group tables
/// `members`, `ids` (one entry per group member): the per-tap tables are derived from
/// `im2col`, empty slots left out.
pub fn pack(
    n: usize,
    im2col: &[usize],
    members: &[usize],
    ids: &[usize],
    num_groups: usize,
) -> (Vec<usize>, ConvLayout) {
    let zero_row = n + num_groups;
    let with_groups = num_groups > 0 && !members.is_empty();
    let m = if with_groups { members.len() } else { 0 };
    let mut packed = Vec::with_capacity(im2col.len() + 2 * m + 2 * im2col.len());
    packed.extend_from_slice(im2col);
    if with_groups {
        packed.extend_from_slice(members);
        packed.extend_from_slice(ids);
    }
    let mut taps = Vec::new();
    let mut occupied = 0usize;
    for f in 0..NUM_TAPS {
        let mut source = Vec::new();
        let mut target = Vec::new();
        for t in 0..n {
            let v = im2col.get(t * NUM_TAPS + f).copied().unwrap_or(zero_row);
            if v != zero_row {
                source.push(v);
                target.push(t);
            }
        }
        if source.is_empty() {
            continue;
        }
        occupied += source.len();
        let full = source.len() == n;
        let identity = full && source.iter().enumerate().all(|(t, &s)| s == t);
        taps.push(ConvTap {
            tap: f,
            len: source.len(),
            full,
            identity,
        });
        packed.extend_from_slice(&source);
        packed.extend_from_slice(&target);
    }
    let occupancy = if n == 0 {
        0.0
    } else {
        occupied as f64 / (NUM_TAPS * n) as f64
    };
    let layout = ConvLayout {
        num_tokens: n,
        num_groups: if with_groups { num_groups } else { 0 },
        num_group_entries: m,
        taps,
        occupancy,
    };
    (packed, layout)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two tokens, one group of both at tap 0, the centre tap the identity: every table lands
    /// at its span.
    #[test]
    fn spans_address_the_packed_tables() {
        let n = 2;
        let zero = n + 1;
        let mut im2col = vec![zero; n * NUM_TAPS];
        im2col[13] = 0;
        im2col[NUM_TAPS + 13] = 1;
        im2col[0] = n; // token 0, tap 0: the group row
        let (packed, layout) = pack(n, &im2col, &[0, 1], &[0, 0], 1);
        assert_eq!(packed.len(), layout.packed_len());
        let (a, len) = layout.im2col();
        assert_eq!(&packed[a..a + len], &im2col[..]);
        let ((ma, ml), (ia, il)) = layout.groups().expect("groups");
        assert_eq!(
            (&packed[ma..ma + ml], &packed[ia..ia + il]),
            (&[0, 1][..], &[0, 0][..])
        );
        let taps: Vec<_> = layout
            .taps
            .iter()
            .map(|t| (t.tap, t.len, t.full, t.identity))
            .collect();
        assert_eq!(taps, vec![(0, 1, false, false), (13, 2, true, true)]);
        let spans = layout.tap_spans();
        let table = |(a, l): Span| packed[a..a + l].to_vec();
        assert_eq!((table(spans[0].0), table(spans[0].1)), (vec![n], vec![0]));
        assert_eq!(
            (table(spans[1].0), table(spans[1].1)),
            (vec![0, 1], vec![0, 1])
        );
        assert!((layout.occupancy - 3.0 / 54.0).abs() < 1e-12);
    }
}
