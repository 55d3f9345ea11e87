//! A small software rasteriser for close-up renders of meshes (the docs' pictures, `canopy species render`):
//! perspective camera, z-buffer, per-pixel interpolated normals and vertex colours, a key light, a fill light and
//! ambient, both faces lit (leaves and bark plates are single-sided), 2×2 supersampling. Pure: it returns pixels.

use crate::mesh::Mesh;
use crate::nearfield::{V3, add, cross, dot, normalize, scale, sub};

/// A perspective camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position.
    pub eye: V3,
    /// The point looked at.
    pub target: V3,
    /// Vertical field of view in degrees.
    pub fov: f64,
}

impl Camera {
    /// A camera that looks at the box `(lo, hi)` from azimuth `azimuth` degrees (about +Y, 0 looks along −Z) and
    /// `elevation` degrees above the horizon, far enough back to frame the box, then `zoom` times closer.
    pub fn framing(lo: [f32; 3], hi: [f32; 3], azimuth: f64, elevation: f64, zoom: f64) -> Camera {
        let (lo, hi) = (lo.map(f64::from), hi.map(f64::from));
        let centre = scale(add(lo, hi), 0.5);
        let radius = 0.5 * libm::sqrt(dot(sub(hi, lo), sub(hi, lo))).max(1e-6);
        let fov: f64 = 35.0;
        let dist = radius / libm::sin(fov.to_radians() / 2.0) / zoom.max(1e-3);
        let (az, el) = (azimuth.to_radians(), elevation.to_radians());
        let dir = [libm::sin(az) * libm::cos(el), libm::sin(el), libm::cos(az) * libm::cos(el)];
        Camera { eye: add(centre, scale(dir, dist)), target: centre, fov }
    }
}

/// An RGB image, row by row from the top, 8 bits per channel.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `3 · width · height` bytes.
    pub rgb: Vec<u8>,
}

/// Largest image side rendered.
pub const MAX_SIDE: u32 = 4096;

/// Render meshes into a `width × height` image over a vertical sky gradient (sides clamped to `1..=4096`).
pub fn render(meshes: &[&Mesh], camera: &Camera, width: u32, height: u32) -> Image {
    let (w, h) = (width.clamp(1, MAX_SIDE), height.clamp(1, MAX_SIDE));
    let (sw, sh) = (2 * w as usize, 2 * h as usize);
    let forward = normalize(sub(camera.target, camera.eye)).unwrap_or([0.0, 0.0, -1.0]);
    let right = normalize(cross(forward, [0.0, 1.0, 0.0])).unwrap_or([1.0, 0.0, 0.0]);
    let up = cross(right, forward);
    let focal = 0.5 * sh as f64 / libm::tan(camera.fov.to_radians() / 2.0);
    let key = normalize([-0.45, 0.8, 0.4]).expect("non-zero");
    let fill = normalize([0.6, 0.2, -0.5]).expect("non-zero");
    let mut depth = vec![f64::INFINITY; sw * sh];
    let mut color = vec![[0.0f64; 3]; sw * sh];
    for y in 0..sh {
        let t = y as f64 / sh as f64;
        for x in 0..sw {
            color[y * sw + x] = [0.62 + 0.25 * t, 0.74 + 0.16 * t, 0.88 + 0.06 * t];
        }
    }
    let project = |p: V3| -> Option<[f64; 3]> {
        let d = sub(p, camera.eye);
        let z = dot(d, forward);
        (z > 1e-4).then(|| [0.5 * sw as f64 + focal * dot(d, right) / z, 0.5 * sh as f64 - focal * dot(d, up) / z, z])
    };
    for m in meshes {
        let screen: Vec<Option<[f64; 3]>> = m.positions.iter().map(|p| project(p.map(f64::from))).collect();
        for t in m.indices.chunks_exact(3) {
            let [i0, i1, i2] = [t[0] as usize, t[1] as usize, t[2] as usize];
            let (Some(a), Some(b), Some(c)) = (screen[i0], screen[i1], screen[i2]) else { continue };
            let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            if area.abs() < 1e-12 {
                continue;
            }
            let x0 = a[0].min(b[0]).min(c[0]).floor().max(0.0) as usize;
            let x1 = (a[0].max(b[0]).max(c[0]).ceil() as i64).clamp(0, sw as i64 - 1) as usize;
            let y0 = a[1].min(b[1]).min(c[1]).floor().max(0.0) as usize;
            let y1 = (a[1].max(b[1]).max(c[1]).ceil() as i64).clamp(0, sh as i64 - 1) as usize;
            if x0 > x1 || y0 > y1 {
                continue;
            }
            let ns = [i0, i1, i2].map(|i| m.normals[i].map(f64::from));
            let cs = [i0, i1, i2].map(|i| m.colors[i].map(f64::from));
            for py in y0..=y1 {
                for px in x0..=x1 {
                    let (qx, qy) = (px as f64 + 0.5, py as f64 + 0.5);
                    let w0 = ((b[0] - qx) * (c[1] - qy) - (b[1] - qy) * (c[0] - qx)) / area;
                    let w1 = ((c[0] - qx) * (a[1] - qy) - (c[1] - qy) * (a[0] - qx)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                        continue;
                    }
                    // Perspective-correct weights.
                    let (p0, p1, p2) = (w0 / a[2], w1 / b[2], w2 / c[2]);
                    let s = p0 + p1 + p2;
                    let z = 1.0 / s;
                    let k = py * sw + px;
                    if z >= depth[k] {
                        continue;
                    }
                    depth[k] = z;
                    let (p0, p1, p2) = (p0 / s, p1 / s, p2 / s);
                    let mut n = normalize(add(add(scale(ns[0], p0), scale(ns[1], p1)), scale(ns[2], p2)))
                        .unwrap_or([0.0, 1.0, 0.0]);
                    if dot(n, forward) > 0.0 {
                        n = scale(n, -1.0);
                    }
                    let light = 0.28 + 0.72 * dot(n, key).max(0.0) + 0.25 * dot(n, fill).max(0.0);
                    let base = add(add(scale(cs[0], p0), scale(cs[1], p1)), scale(cs[2], p2));
                    color[k] = base.map(|x| x * light);
                }
            }
        }
    }
    let mut rgb = Vec::with_capacity(3 * (w * h) as usize);
    for y in 0..h as usize {
        for x in 0..w as usize {
            let mut sum = [0.0f64; 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let c = color[(2 * y + dy) * sw + 2 * x + dx];
                for k in 0..3 {
                    sum[k] += c[k];
                }
            }
            // Linear to sRGB-ish gamma.
            for s in sum {
                let v = libm::pow((s / 4.0).clamp(0.0, 1.0), 1.0 / 2.2);
                rgb.push((v * 255.0 + 0.5) as u8);
            }
        }
    }
    Image { width: w, height: h, rgb }
}

impl Image {
    /// The image as PNG bytes.
    pub fn png(&self) -> Result<Vec<u8>, image::ImageError> {
        use image::ImageEncoder;
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out).write_image(
            &self.rgb,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )?;
        Ok(out)
    }
}
