//! Screen tiles of the far field, pure (no GPU): which far instances and forest patches each 16 × 16-pixel tile
//! of the target may show, in drawing order (front to back), for the compute pass that marches them
//! (`shaders/far_march.wgsl`): each pixel walks its tile's list, compositing what its ray meets until it is opaque.
//! An item is listed in every tile its box's projection touches (the whole screen where the box reaches behind
//! the eye; nowhere where it lies wholly behind).

use glam::{Mat4, Vec3, Vec4Swizzles};

/// Pixels along a tile's side (the compute pass's workgroup is one tile).
pub(crate) const TILE_PX: u32 = 16;

/// The bit of an item that marks a forest patch (clear: a far instance); the rest is its index.
pub(crate) const PATCH_BIT: u32 = 1 << 31;

/// Most items listed in one frame; beyond it the farthest go unlisted (a bound on the frame's memory whatever the
/// scene).
pub(crate) const MAX_ENTRIES: usize = 1 << 24;

/// The frame's tile lists: `items[offsets[t]..offsets[t + 1]]` for tile `t` (row-major).
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct TileBins {
    /// Tiles across and down.
    pub tiles: (u32, u32),
    /// Where each tile's list starts in `items`, and one more for the end.
    pub offsets: Vec<u32>,
    /// Items, tile after tile.
    pub items: Vec<u32>,
    /// Each item with its tile rectangle (x0, y0, x1, y1 inclusive), in drawing order.
    rects: Vec<(u32, [u32; 4])>,
}

impl TileBins {
    /// Start a frame for a `size` target.
    pub(crate) fn begin(&mut self, size: (u32, u32)) {
        self.tiles = (size.0.div_ceil(TILE_PX).max(1), size.1.div_ceil(TILE_PX).max(1));
        self.rects.clear();
    }

    /// Add `item` (in drawing order) whose box `lo..hi` (world space) projects through `view_proj` onto a `size`
    /// target; nothing if it is wholly off screen.
    pub(crate) fn add(&mut self, item: u32, lo: Vec3, hi: Vec3, view_proj: &Mat4, size: (u32, u32)) {
        let (mut min, mut max) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        let mut behind = 0;
        for k in 0..8 {
            let c = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            let clip = *view_proj * c.extend(1.0);
            if clip.w <= 1e-3 {
                behind += 1;
                continue;
            }
            let ndc = clip.xy() / clip.w;
            for a in 0..2 {
                min[a] = min[a].min(ndc[a]);
                max[a] = max[a].max(ndc[a]);
            }
        }
        match behind {
            8 => return,
            0 => {}
            // Reaching behind the eye: its projection is unbounded.
            _ => (min, max) = ([-1.0, -1.0], [1.0, 1.0]),
        }
        if !(min[0] <= 1.0 && max[0] >= -1.0 && min[1] <= 1.0 && max[1] >= -1.0) {
            return;
        }
        let (w, h) = (size.0.max(1) as f32, size.1.max(1) as f32);
        // Pixels: x right, y down (ndc y up).
        let px = |x: f32| ((x * 0.5 + 0.5) * w).clamp(0.0, w - 1.0);
        let py = |y: f32| ((0.5 - y * 0.5) * h).clamp(0.0, h - 1.0);
        let t = |p: f32| p as u32 / TILE_PX;
        self.rects.push((item, [t(px(min[0])), t(py(max[1])), t(px(max[0])), t(py(min[1]))]));
    }

    /// Fill the lists (a counting sort: each tile keeps the drawing order).
    pub(crate) fn finish(&mut self) {
        let (tx, ty) = self.tiles;
        let n = (tx * ty) as usize;
        self.offsets.clear();
        self.offsets.resize(n + 1, 0);
        let mut total = 0usize;
        let mut listed = 0;
        for (_, r) in &self.rects {
            let area = ((r[2] - r[0] + 1) * (r[3] - r[1] + 1)) as usize;
            if total + area > MAX_ENTRIES {
                break;
            }
            total += area;
            listed += 1;
            for y in r[1]..=r[3] {
                for x in r[0]..=r[2] {
                    self.offsets[(y * tx + x) as usize + 1] += 1;
                }
            }
        }
        for t in 0..n {
            self.offsets[t + 1] += self.offsets[t];
        }
        self.items.clear();
        self.items.resize(total, 0);
        let mut next: Vec<u32> = self.offsets[..n].to_vec();
        for (item, r) in &self.rects[..listed] {
            for y in r[1]..=r[3] {
                for x in r[0]..=r[2] {
                    let t = (y * tx + x) as usize;
                    self.items[next[t] as usize] = *item;
                    next[t] += 1;
                }
            }
        }
        if self.items.is_empty() {
            // Never an empty buffer.
            self.items.push(0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> Mat4 {
        // From the origin looking down -z, 90° vertical field of view, square.
        crate::camera::Camera::looking_at(Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0), 90.0).view_projection(1.0, 0.1)
    }

    #[test]
    fn items_are_listed_in_the_tiles_they_cover_in_order() {
        let mut b = TileBins::default();
        let size = (64, 64);
        b.begin(size);
        // A small box straight ahead: the middle four tiles.
        b.add(7, Vec3::new(-0.1, -0.1, -10.1), Vec3::new(0.1, 0.1, -9.9), &view(), size);
        // A box in the upper left quarter, then one behind the eye (nothing), then one around the eye (everywhere).
        b.add(PATCH_BIT | 2, Vec3::new(-10.0, 1.0, -10.0), Vec3::new(-1.0, 10.0, -9.0), &view(), size);
        b.add(3, Vec3::new(-1.0, -1.0, 5.0), Vec3::new(1.0, 1.0, 6.0), &view(), size);
        b.add(9, Vec3::splat(-1.0), Vec3::splat(1.0), &view(), size);
        b.finish();
        assert_eq!(b.tiles, (4, 4));
        let list = |x: u32, y: u32| {
            let t = (y * 4 + x) as usize;
            b.items[b.offsets[t] as usize..b.offsets[t + 1] as usize].to_vec()
        };
        assert_eq!(list(1, 1), vec![7, PATCH_BIT | 2, 9]);
        assert_eq!(list(2, 2), vec![7, 9]);
        assert_eq!(list(0, 0), vec![PATCH_BIT | 2, 9]);
        assert_eq!(list(3, 3), vec![9]);
        assert_eq!(b.offsets[16], 4 + 4 + 16);
    }

    #[test]
    fn nothing_in_view_lists_nothing_but_keeps_a_buffer() {
        let mut b = TileBins::default();
        b.begin((100, 50));
        b.add(1, Vec3::new(100.0, 0.0, -1.0), Vec3::new(101.0, 1.0, -0.5), &view(), (100, 50));
        b.finish();
        assert_eq!((b.tiles, b.offsets.len(), b.offsets[28], b.items.len()), ((7, 4), 29, 0, 1));
    }
}
