//! The per-pixel network input of one chunk (`network.md` §2): normalised dense points, raw
//! confidence, normalised DLT points and their mask.
//!
//! One Burn-free definition shared by the planner (`ggpt_model::plan`, which re-exports
//! [`ChunkInput`]), the scene pipeline's chunk records (`ggpt_scene::record::ChunkRecord` embeds
//! a [`ChunkInput`]) and the training chunks (`ggpt_train::chunkset::TrainChunk`). The planner
//! reads chunks through [`AsChunkView`], so a forward borrows the records it plans instead of
//! copying their arrays.

/// One chunk's network input (`network.md` §2). All vectors are in pixel order and have the same
/// length `K`. Points are in normalised chunk coordinates `(x - c) / r` (not clipped); `ff_conf`
/// is the raw feed-forward confidence (`1 + exp` scale). Rows of `geo_pts` with `geo_msk` false
/// are ignored by the network (they may hold any value, including non-finite ones).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChunkInput {
    /// Dense feed-forward point of each pixel, normalised chunk coordinates, `[K]`.
    pub ff_pts: Vec<[f32; 3]>,
    /// Raw feed-forward confidence of each pixel, `[K]`.
    pub ff_conf: Vec<f32>,
    /// DLT guidance point of each pixel, normalised chunk coordinates, `[K]` (used where `geo_msk`).
    pub geo_pts: Vec<[f32; 3]>,
    /// Whether the pixel has a DLT point (and hence a DLT token), `[K]`.
    pub geo_msk: Vec<bool>,
}

impl ChunkInput {
    /// Pixels (dense tokens) `K = ff_pts.len()`.
    pub fn len(&self) -> usize {
        self.ff_pts.len()
    }
    /// True when the chunk has no pixel.
    pub fn is_empty(&self) -> bool {
        self.ff_pts.is_empty()
    }
    /// The borrowed form read by the planner.
    pub fn view(&self) -> ChunkView<'_> {
        ChunkView {
            ff_pts: &self.ff_pts,
            ff_conf: &self.ff_conf,
            geo_pts: &self.geo_pts,
            geo_msk: &self.geo_msk,
        }
    }
}

/// A borrowed [`ChunkInput`]: the four per-pixel arrays of one chunk, in pixel order (same
/// meaning and conventions as the fields of [`ChunkInput`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChunkView<'a> {
    /// Dense feed-forward points, normalised chunk coordinates, `[K]`.
    pub ff_pts: &'a [[f32; 3]],
    /// Raw feed-forward confidence, `[K]`.
    pub ff_conf: &'a [f32],
    /// DLT guidance points, normalised chunk coordinates, `[K]` (used where `geo_msk`).
    pub geo_pts: &'a [[f32; 3]],
    /// Whether the pixel has a DLT point, `[K]`.
    pub geo_msk: &'a [bool],
}

impl ChunkView<'_> {
    /// An owned copy.
    pub fn to_input(&self) -> ChunkInput {
        ChunkInput {
            ff_pts: self.ff_pts.to_vec(),
            ff_conf: self.ff_conf.to_vec(),
            geo_pts: self.geo_pts.to_vec(),
            geo_msk: self.geo_msk.to_vec(),
        }
    }
}

/// Anything the planner can read a chunk's network input from without copying it: a
/// [`ChunkInput`], a [`ChunkView`], a reference to either, or a record type that holds the four
/// per-pixel arrays (chunk records, training chunks).
pub trait AsChunkView {
    /// The chunk's per-pixel network input, borrowed.
    fn chunk_view(&self) -> ChunkView<'_>;
}

impl AsChunkView for ChunkInput {
    fn chunk_view(&self) -> ChunkView<'_> {
        self.view()
    }
}

impl AsChunkView for ChunkView<'_> {
    fn chunk_view(&self) -> ChunkView<'_> {
        *self
    }
}

impl<T: AsChunkView + ?Sized> AsChunkView for &T {
    fn chunk_view(&self) -> ChunkView<'_> {
        (**self).chunk_view()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_borrow_the_same_arrays() {
        let c = ChunkInput {
            ff_pts: vec![[0.1, 0.2, 0.3]],
            ff_conf: vec![1.5],
            geo_pts: vec![[0.0; 3]],
            geo_msk: vec![true],
        };
        let by_ref = &&c;
        let v = by_ref.chunk_view();
        assert!(std::ptr::eq(v.ff_pts, c.ff_pts.as_slice()));
        assert_eq!(v.to_input(), c);
        assert_eq!(v.chunk_view(), v);
        assert_eq!((c.len(), c.is_empty()), (1, false));
    }
}
