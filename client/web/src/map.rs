//! The map's pixels: a top-down view around the camera, heading up, the ground shaded by height and each instance
//! held a dot coloured by species. Pure (an RGBA buffer the page puts on its canvas once a frame), so it is tested
//! natively; the lines drawn over it (the area of interest, the camera) are the page's.
//!
//! Heights are sampled on a world-aligned lattice, memoised, and at most [`NEW_SAMPLES_PER_FRAME`] new ones are
//! computed a frame (a fractal ground's height costs microseconds): moving reveals the ground over a few frames,
//! and turning costs no sample.

use std::collections::HashMap;

use canopy_protocol::record::dequantize;

use crate::camera::Camera;
use crate::session::Session;

/// Screen pixels a ground sample covers (a square block).
pub const BLOCK: usize = 8;
/// Most new height samples a frame.
pub const NEW_SAMPLES_PER_FRAME: usize = 1500;
/// Most samples memoised (past it the memo starts over).
const MAX_SAMPLES: usize = 200_000;

/// A species' dot colour: hues a golden angle apart, so neighbouring ids differ.
pub fn species_colour(id: u8) -> [u8; 3] {
    let h = (f32::from(id) * 137.507_77).rem_euclid(360.0) / 60.0;
    let (s, v) = (0.75, 0.95);
    let c = v * s;
    let x = c * (1.0 - (h.rem_euclid(2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    let byte = |f: f32| ((f + m) * 255.0).round().clamp(0.0, 255.0) as u8;
    [byte(r), byte(g), byte(b)]
}

/// The map's framing: the canvas size and how many metres a pixel covers, around the camera, heading up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Canvas width, pixels.
    pub width: usize,
    /// Canvas height, pixels.
    pub height: usize,
    /// Metres a pixel.
    pub metres_per_px: f32,
    /// The camera on (x, z).
    pub centre: [f32; 2],
    /// `(sin yaw, cos yaw)`: screen up.
    pub heading: [f32; 2],
    /// `(−cos yaw, sin yaw)`: screen right.
    pub right: [f32; 2],
}

impl Frame {
    /// A frame of `width` × `height` around `camera` showing `span` metres from the centre to the nearer edge.
    pub fn new(width: usize, height: usize, camera: &Camera, span: f32) -> Frame {
        let half = (width.min(height) as f32 * 0.5).max(1.0);
        Frame {
            width,
            height,
            metres_per_px: (span / half).max(1e-3),
            centre: [camera.position[0], camera.position[2]],
            heading: camera.heading(),
            right: camera.right(),
        }
    }

    /// The screen position of world point (x, z).
    pub fn to_screen(&self, p: [f32; 2]) -> [f32; 2] {
        let d = [p[0] - self.centre[0], p[1] - self.centre[1]];
        let r = d[0] * self.right[0] + d[1] * self.right[1];
        let f = d[0] * self.heading[0] + d[1] * self.heading[1];
        [self.width as f32 * 0.5 + r / self.metres_per_px, self.height as f32 * 0.5 - f / self.metres_per_px]
    }

    /// The world point (x, z) under screen position `s`.
    pub fn to_world(&self, s: [f32; 2]) -> [f32; 2] {
        let r = (s[0] - self.width as f32 * 0.5) * self.metres_per_px;
        let f = (self.height as f32 * 0.5 - s[1]) * self.metres_per_px;
        [
            self.centre[0] + r * self.right[0] + f * self.heading[0],
            self.centre[1] + r * self.right[1] + f * self.heading[1],
        ]
    }
}

/// The map's RGBA pixels and its memo of ground heights.
#[derive(Debug, Default)]
pub struct Map {
    /// RGBA, row by row, `width × height × 4` bytes.
    pub pixels: Vec<u8>,
    width: usize,
    height: usize,
    /// Heights by lattice point, at `spacing` metres.
    samples: HashMap<(i32, i32), f32>,
    spacing: f32,
    /// The range of heights seen last frame, for the shading.
    range: [f32; 2],
    /// Dots drawn last frame.
    pub dots: usize,
}

impl Map {
    /// Paint the ground and the held instances of `session` in `frame`.
    pub fn paint(&mut self, session: &Session, frame: &Frame) {
        if (frame.width, frame.height) != (self.width, self.height) {
            self.width = frame.width;
            self.height = frame.height;
            self.pixels = vec![0; frame.width * frame.height * 4];
        }
        self.ground(session, frame);
        self.instances(session, frame);
    }

    fn ground(&mut self, session: &Session, frame: &Frame) {
        // A lattice whose step is about a block, in powers of two metres (the memo survives small zooms).
        let want = frame.metres_per_px * BLOCK as f32;
        let spacing = 2f32.powi(want.max(1e-3).log2().round() as i32);
        if spacing != self.spacing || self.samples.len() > MAX_SAMPLES {
            self.samples.clear();
            self.spacing = spacing;
        }
        let plain = [34u8, 40, 36];
        let (bw, bh) = (frame.width.div_ceil(BLOCK), frame.height.div_ceil(BLOCK));
        let mut budget = NEW_SAMPLES_PER_FRAME;
        let mut seen = [f32::INFINITY, f32::NEG_INFINITY];
        let [lo, hi] = self.range;
        let scale = if hi > lo { 1.0 / (hi - lo) } else { 0.0 };
        for by in 0..bh {
            for bx in 0..bw {
                let centre = [(bx * BLOCK) as f32 + BLOCK as f32 * 0.5, (by * BLOCK) as f32 + BLOCK as f32 * 0.5];
                let colour = match (session.ground(), self.sample(session, frame.to_world(centre), &mut budget)) {
                    (Some(_), Some((h, dh))) => {
                        seen = [seen[0].min(h), seen[1].max(h)];
                        let t = ((h - lo) * scale).clamp(0.0, 1.0);
                        // Lit from the north-west: a slope rising that way is brighter.
                        let light = (1.0 + (dh / spacing).clamp(-1.0, 1.0) * 0.35).clamp(0.6, 1.35);
                        let base = [40.0 + 70.0 * t, 58.0 + 62.0 * t, 40.0 + 40.0 * t];
                        base.map(|c: f32| (c * light).clamp(0.0, 255.0) as u8)
                    }
                    _ => plain,
                };
                self.fill_block(bx * BLOCK, by * BLOCK, colour);
            }
        }
        if seen[0] <= seen[1] {
            self.range = seen;
        }
    }

    /// The height at the lattice point nearest `p` and its rise from the point one step north-west, computing at
    /// most `budget` new points.
    fn sample(&mut self, session: &Session, p: [f32; 2], budget: &mut usize) -> Option<(f32, f32)> {
        session.ground()?;
        let s = self.spacing;
        let key = ((p[0] / s).round() as i32, (p[1] / s).round() as i32);
        let mut get = |k: (i32, i32)| -> Option<f32> {
            if let Some(h) = self.samples.get(&k) {
                return Some(*h);
            }
            if *budget == 0 {
                return None;
            }
            *budget -= 1;
            let h = session.height(k.0 as f32 * s, k.1 as f32 * s);
            self.samples.insert(k, h);
            Some(h)
        };
        let h = get(key)?;
        let dh = get((key.0 + 1, key.1 + 1)).map_or(0.0, |n| h - n);
        Some((h, dh))
    }

    fn fill_block(&mut self, x0: usize, y0: usize, rgb: [u8; 3]) {
        for y in y0..(y0 + BLOCK).min(self.height) {
            let row = y * self.width * 4;
            for x in x0..(x0 + BLOCK).min(self.width) {
                let i = row + x * 4;
                self.pixels[i..i + 4].copy_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
            }
        }
    }

    fn instances(&mut self, session: &Session, frame: &Frame) {
        self.dots = 0;
        let state = session.state();
        let Some(w) = state.welcome() else { return };
        let grid = &w.world.grid;
        let colours: Vec<[u8; 3]> = (0..w.species.len()).map(|i| species_colour(i as u8)).collect();
        let half_diag = ((frame.width * frame.width + frame.height * frame.height) as f32).sqrt() * 0.5;
        let reach = half_diag * frame.metres_per_px + grid.cell_size;
        // Dots are 2 px, 3 px when zoomed in.
        let size: i32 = if frame.metres_per_px < 0.5 { 3 } else { 2 };
        for (c, h) in state.cells() {
            let origin = grid.cell_origin(*c);
            let mid = [origin[0] + grid.cell_size * 0.5, origin[1] + grid.cell_size * 0.5];
            let d = [mid[0] - frame.centre[0], mid[1] - frame.centre[1]];
            if d[0] * d[0] + d[1] * d[1] > reach * reach {
                continue;
            }
            for (i, r) in h.records.iter().enumerate() {
                if !h.felled.is_empty() && h.felled.contains(&(i as u16)) {
                    continue;
                }
                let x = dequantize(r.qx(), origin[0], grid.cell_size);
                let z = dequantize(r.qz(), origin[1], grid.cell_size);
                let s = frame.to_screen([x, z]);
                let rgb = colours.get(usize::from(r.species)).copied().unwrap_or([255, 255, 255]);
                if self.dot(s, size, rgb) {
                    self.dots += 1;
                }
            }
        }
    }

    fn dot(&mut self, s: [f32; 2], size: i32, rgb: [u8; 3]) -> bool {
        let (x0, y0) = (s[0] as i32 - size / 2, s[1] as i32 - size / 2);
        if x0 + size <= 0 || y0 + size <= 0 || x0 >= self.width as i32 || y0 >= self.height as i32 {
            return false;
        }
        for y in y0.max(0)..(y0 + size).min(self.height as i32) {
            for x in x0.max(0)..(x0 + size).min(self.width as i32) {
                let i = (y as usize * self.width + x as usize) * 4;
                self.pixels[i..i + 4].copy_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn screen_and_world_are_inverse_and_heading_is_up() {
        let mut camera = Camera::default();
        camera.position = [100.0, 5.0, -40.0];
        camera.yaw = 0.7;
        let f = Frame::new(800, 600, &camera, 300.0);
        assert_eq!(f.to_screen([100.0, -40.0]), [400.0, 300.0]);
        let ahead = [100.0 + 50.0 * 0.7f32.sin(), -40.0 + 50.0 * 0.7f32.cos()];
        let s = f.to_screen(ahead);
        assert!((s[0] - 400.0).abs() < 1e-3 && s[1] < 300.0, "ahead is straight up: {s:?}");
        let r = camera.right();
        assert!(f.to_screen([100.0 + 10.0 * r[0], -40.0 + 10.0 * r[1]])[0] > 400.0, "right is right");
        let w = f.to_world([123.0, 456.0]);
        let back = f.to_screen(w);
        assert!((back[0] - 123.0).abs() < 1e-2 && (back[1] - 456.0).abs() < 1e-2);
    }

    #[test]
    fn species_colours_are_bright_and_distinct() {
        let all: Vec<[u8; 3]> = (0..16).map(species_colour).collect();
        for (i, a) in all.iter().enumerate() {
            assert!(a.iter().any(|&c| c > 200), "{a:?}");
            assert!(all[i + 1..].iter().all(|b| b != a));
        }
    }

    #[test]
    fn a_map_before_the_welcome_is_plain_ground() {
        let session = Session::new(Default::default());
        let mut map = Map::default();
        map.paint(&session, &Frame::new(20, 10, &Camera::default(), 100.0));
        assert_eq!(map.pixels.len(), 20 * 10 * 4);
        assert!(map.pixels.chunks(4).all(|p| p == [34, 40, 36, 255]));
        assert_eq!(map.dots, 0);
    }
}
