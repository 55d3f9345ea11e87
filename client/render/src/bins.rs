//! Screen tiles of the far field, pure (no GPU): which far instances and forest patches each 16 × 16-pixel tile
//! of the target may show, in drawing order (front to back), for the compute pass that marches them
//! (`shaders/far_march.wgsl`): each pixel walks its tile's list, compositing what its ray meets until it is opaque.
//! An item is listed in every tile its box's projection touches (the whole screen where the box reaches behind
//! the eye; nowhere where it lies wholly behind).

use canopy_worlds::world::par;
use glam::{Mat4, Vec3, Vec4Swizzles};

/// Pixels along a tile's side (the compute pass's workgroup is one tile).
pub(crate) const TILE_PX: u32 = 16;

/// The bit of an item that marks a forest patch (clear: a far instance); the rest is its index.
pub(crate) const PATCH_BIT: u32 = 1 << 31;

/// Items whose projections one job takes ([`TileBins::add_all`]).
const PARALLEL_CHUNK: usize = 4096;
/// Most bands of tile rows the lists are filled in, a job each, one a core ([`TileBins::finish`]).
const MAX_BANDS: u32 = 16;

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

    /// Add `items` (item, box in world space), in drawing order, each projected through `view_proj` onto a `size`
    /// target (nothing for one wholly off screen); their projections are taken on every core.
    pub(crate) fn add_all(&mut self, items: &[(u32, Vec3, Vec3)], view_proj: &Mat4, size: (u32, u32)) {
        let chunks: Vec<&[(u32, Vec3, Vec3)]> = items.chunks(PARALLEL_CHUNK).collect();
        let rects = par::map(
            &chunks,
            || (),
            |_, chunk| {
                chunk
                    .iter()
                    .filter_map(|&(item, lo, hi)| Some((item, tile_rect(lo, hi, view_proj, size)?)))
                    .collect::<Vec<_>>()
            },
        );
        self.rects.extend(rects.into_iter().flatten());
    }

    /// Fill the lists (a counting sort: each tile keeps the drawing order), a band of tile rows a core: the rows'
    /// lists lie together, so each band's part is its own.
    pub(crate) fn finish(&mut self) {
        let (tx, ty) = self.tiles;
        let n = (tx * ty) as usize;
        // The items listed: in drawing order, until the entries would pass the bound.
        let mut total = 0usize;
        let mut listed = 0;
        for (_, r) in &self.rects {
            let area = ((r[2] - r[0] + 1) * (r[3] - r[1] + 1)) as usize;
            if total + area > MAX_ENTRIES {
                break;
            }
            total += area;
            listed += 1;
        }
        let rects = &self.rects[..listed];
        // As many bands as cores, each with the items (indices into `rects`, in order) that reach its rows.
        let cores = std::thread::available_parallelism().map_or(1, |c| c.get()).min(MAX_BANDS as usize) as u32;
        let rows = ty.div_ceil(cores).max(1);
        let bands: Vec<(u32, u32)> = (0..ty).step_by(rows as usize).map(|y0| (y0, (y0 + rows).min(ty))).collect();
        let mut reach: Vec<Vec<u32>> = vec![Vec::new(); bands.len()];
        for (k, (_, r)) in rects.iter().enumerate() {
            for band in reach.iter_mut().take((r[3] / rows) as usize + 1).skip((r[1] / rows) as usize) {
                band.push(k as u32);
            }
        }
        let jobs: Vec<((u32, u32), &[u32])> = bands.iter().copied().zip(reach.iter().map(Vec::as_slice)).collect();
        // Each band's tiles' counts, then every tile's offset.
        let counts = par::map(
            &jobs,
            || (),
            |_, &((y0, y1), reach)| {
                let mut c = vec![0u32; ((y1 - y0) * tx) as usize];
                for &k in reach {
                    let r = rects[k as usize].1;
                    for y in r[1].max(y0)..=r[3].min(y1 - 1) {
                        for x in r[0]..=r[2] {
                            c[((y - y0) * tx + x) as usize] += 1;
                        }
                    }
                }
                c
            },
        );
        self.offsets.clear();
        self.offsets.push(0);
        let mut at = 0;
        for c in counts.iter().flatten() {
            at += c;
            self.offsets.push(at);
        }
        debug_assert_eq!(self.offsets.len(), n + 1);
        let offsets = &self.offsets;
        let parts = par::map(
            &jobs,
            || (),
            |_, &((y0, y1), reach)| {
                let base = offsets[(y0 * tx) as usize];
                let mut next: Vec<u32> =
                    offsets[(y0 * tx) as usize..(y1 * tx) as usize].iter().map(|o| o - base).collect();
                let mut part = vec![0u32; (offsets[(y1 * tx) as usize] - base) as usize];
                for &k in reach {
                    let (item, r) = rects[k as usize];
                    for y in r[1].max(y0)..=r[3].min(y1 - 1) {
                        for x in r[0]..=r[2] {
                            let t = ((y - y0) * tx + x) as usize;
                            part[next[t] as usize] = item;
                            next[t] += 1;
                        }
                    }
                }
                part
            },
        );
        self.items.clear();
        self.items.reserve(total);
        for p in parts {
            self.items.extend_from_slice(&p);
        }
        if self.items.is_empty() {
            // Never an empty buffer.
            self.items.push(0);
        }
    }
}

/// The tile rectangle (x0, y0, x1, y1 inclusive) the box `lo..hi` projects onto through `view_proj` on a `size`
/// target; `None` if it is wholly off screen or behind the eye.
fn tile_rect(lo: Vec3, hi: Vec3, view_proj: &Mat4, size: (u32, u32)) -> Option<[u32; 4]> {
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
        8 => return None,
        0 => {}
        // Reaching behind the eye: its projection is unbounded.
        _ => (min, max) = ([-1.0, -1.0], [1.0, 1.0]),
    }
    if !(min[0] <= 1.0 && max[0] >= -1.0 && min[1] <= 1.0 && max[1] >= -1.0) {
        return None;
    }
    let (w, h) = (size.0.max(1) as f32, size.1.max(1) as f32);
    // Pixels: x right, y down (ndc y up).
    let px = |x: f32| ((x * 0.5 + 0.5) * w).clamp(0.0, w - 1.0);
    let py = |y: f32| ((0.5 - y * 0.5) * h).clamp(0.0, h - 1.0);
    let t = |p: f32| p as u32 / TILE_PX;
    Some([t(px(min[0])), t(py(max[1])), t(px(max[0])), t(py(min[1]))])
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
        let items = [
            (7, Vec3::new(-0.1, -0.1, -10.1), Vec3::new(0.1, 0.1, -9.9)),
            // A box in the upper left quarter, then one behind the eye (nothing), then one around the eye
            // (everywhere).
            (PATCH_BIT | 2, Vec3::new(-10.0, 1.0, -10.0), Vec3::new(-1.0, 10.0, -9.0)),
            (3, Vec3::new(-1.0, -1.0, 5.0), Vec3::new(1.0, 1.0, 6.0)),
            (9, Vec3::splat(-1.0), Vec3::splat(1.0)),
        ];
        b.add_all(&items, &view(), size);
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
        b.add_all(&[(1, Vec3::new(100.0, 0.0, -1.0), Vec3::new(101.0, 1.0, -0.5))], &view(), (100, 50));
        b.finish();
        assert_eq!((b.tiles, b.offsets.len(), b.offsets[28], b.items.len()), ((7, 4), 29, 0, 1));
    }

    #[test]
    fn many_items_over_many_rows_list_as_one_at_a_time_would() {
        // More items than a job takes and more tile rows than bands: every tile's list is the items covering it, in
        // order, however the work was split.
        let size = (640, 480);
        let mut state = 1u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1 << 24) as f32
        };
        let items: Vec<(u32, Vec3, Vec3)> = (0..10_000u32)
            .map(|i| {
                let c = Vec3::new(next() * 40.0 - 20.0, next() * 30.0 - 15.0, -5.0 - next() * 30.0);
                let r = 0.05 + next() * 2.0;
                (i, c - Vec3::splat(r), c + Vec3::splat(r))
            })
            .collect();
        let mut b = TileBins::default();
        b.begin(size);
        b.add_all(&items, &view(), size);
        b.finish();
        let (tx, ty) = b.tiles;
        let rects: Vec<(u32, [u32; 4])> =
            items.iter().filter_map(|&(i, lo, hi)| Some((i, tile_rect(lo, hi, &view(), size)?))).collect();
        assert!(rects.len() > 5_000);
        for t in 0..tx * ty {
            let (x, y) = (t % tx, t / tx);
            let want: Vec<u32> = rects
                .iter()
                .filter(|(_, r)| (r[0]..=r[2]).contains(&x) && (r[1]..=r[3]).contains(&y))
                .map(|&(i, _)| i)
                .collect();
            assert_eq!(
                b.items[b.offsets[t as usize] as usize..b.offsets[t as usize + 1] as usize],
                want[..],
                "tile {t}"
            );
        }
    }
}
