//! The camera: a position, yaw and pitch, a vertical field of view; its matrices (reversed-Z, infinite far plane)
//! and frustum; and the camera file of `canopy render --camera`.
//!
//! # Camera files
//!
//! One statement per line (or separated by `;` when given inline); `#` starts a comment.
//!
//! ```text
//! position 0 ~30 -600     # x y z in metres; `~h` for y means h metres above the terrain at (x, z)
//! look-at 0 ~10 0         # a point to look at (same `~` rule) …
//! yaw 0                   # … or a heading in degrees (0 looks along +z, 90 along +x)
//! pitch -10               #     and a pitch in degrees (negative looks down)
//! fov 60                  # vertical field of view, degrees (default 60)
//! ```
//!
//! `position` is required; `look-at` and `yaw`/`pitch` exclude each other.

use glam::{Mat4, Vec3, Vec4};

/// Largest coordinate a camera may have, metres.
pub const MAX_COORDINATE: f32 = 1.0e6;
/// Largest camera file, bytes.
pub const MAX_CAMERA_FILE: u64 = 64 * 1024;

/// A viewpoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position, world metres (+Y up).
    pub position: Vec3,
    /// Heading in radians: 0 looks along +z, π/2 along +x (the protocol's `(sin yaw, cos yaw)`).
    pub yaw: f32,
    /// Pitch in radians, positive looks up; kept within ±89°.
    pub pitch: f32,
    /// Vertical field of view, degrees.
    pub fov_y: f32,
}

impl Camera {
    /// A camera at `position` looking at `target`.
    pub fn looking_at(position: Vec3, target: Vec3, fov_y: f32) -> Camera {
        let d = target - position;
        let horizontal = (d.x * d.x + d.z * d.z).sqrt();
        let (yaw, pitch) = if d.length_squared() > 0.0 { (d.x.atan2(d.z), d.y.atan2(horizontal)) } else { (0.0, 0.0) };
        Camera { position, yaw, pitch: clamp_pitch(pitch), fov_y }
    }

    /// The unit view direction.
    pub fn forward(&self) -> Vec3 {
        let (sp, cp) = self.pitch.sin_cos();
        let (sy, cy) = self.yaw.sin_cos();
        Vec3::new(cp * sy, sp, cp * cy)
    }

    /// The unit right vector (horizontal).
    pub fn right(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        Vec3::new(-cy, 0.0, sy)
    }

    /// The view matrix (right-handed, looking down −z in view space).
    pub fn view(&self) -> Mat4 {
        let f = self.forward();
        let s = f.cross(Vec3::Y).normalize_or(Vec3::X);
        let u = s.cross(f);
        let e = self.position;
        Mat4::from_cols(
            Vec4::new(s.x, u.x, -f.x, 0.0),
            Vec4::new(s.y, u.y, -f.y, 0.0),
            Vec4::new(s.z, u.z, -f.z, 0.0),
            Vec4::new(-s.dot(e), -u.dot(e), f.dot(e), 1.0),
        )
    }

    /// The projection: reversed-Z (depth 1 at the near plane, 0 at infinity), infinite far plane.
    pub fn projection(&self, aspect: f32, near: f32) -> Mat4 {
        // A view-space point at distance d in front (z = −d) gets depth near / d.
        let f = 1.0 / self.tan_half_fov();
        Mat4::from_cols(
            Vec4::new(f / aspect, 0.0, 0.0, 0.0),
            Vec4::new(0.0, f, 0.0, 0.0),
            Vec4::new(0.0, 0.0, 0.0, -1.0),
            Vec4::new(0.0, 0.0, near, 0.0),
        )
    }

    /// Projection times view.
    pub fn view_projection(&self, aspect: f32, near: f32) -> Mat4 {
        self.projection(aspect, near) * self.view()
    }

    /// `tan(fov_y / 2)`.
    pub fn tan_half_fov(&self) -> f32 {
        (self.fov_y.to_radians() * 0.5).tan()
    }

    /// Turn by mouse deltas (radians), keeping the pitch within ±89°.
    pub fn turn(&mut self, d_yaw: f32, d_pitch: f32) {
        self.yaw = (self.yaw + d_yaw).rem_euclid(std::f32::consts::TAU);
        self.pitch = clamp_pitch(self.pitch + d_pitch);
    }
}

fn clamp_pitch(p: f32) -> f32 {
    let lim = 89f32.to_radians();
    p.clamp(-lim, lim)
}

/// The side planes and near plane of a view frustum, for sphere culling (`n · p + d ≥ −r` is inside).
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    planes: [Vec4; 5],
}

impl Frustum {
    /// The frustum of a reversed-Z, infinite-far view-projection matrix (Gribb–Hartmann plane extraction).
    pub fn from_matrix(m: Mat4) -> Frustum {
        let r = m.transpose();
        let (r0, r1, r2, r3) = (r.x_axis, r.y_axis, r.z_axis, r.w_axis);
        // Reversed Z: 0 ≤ z/w ≤ 1 with the near plane at z = w.
        let planes = [r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 - r2].map(|p| {
            let n = p.truncate().length();
            if n > 0.0 { p / n } else { p }
        });
        Frustum { planes }
    }

    /// The planes `(n, d)`, `n` a unit vector: the four sides, then the near plane.
    pub(crate) fn planes(&self) -> [Vec4; 5] {
        self.planes
    }

    /// Whether a sphere is at least partly inside.
    #[inline]
    pub fn sphere_visible(&self, center: Vec3, radius: f32) -> bool {
        self.planes.iter().all(|p| p.truncate().dot(center) + p.w >= -radius)
    }
}

/// A coordinate of a camera file: absolute, or `~h` above the terrain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Height {
    /// Absolute y.
    Absolute(f32),
    /// Metres above the terrain at (x, z).
    AboveGround(f32),
}

/// A parsed camera file, before heights above the terrain are resolved.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraSpec {
    /// x, y, z.
    pub position: (f32, Height, f32),
    /// What the camera looks at.
    pub aim: Aim,
    /// Vertical field of view, degrees.
    pub fov_y: f32,
}

/// Where a camera looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Aim {
    /// At a point.
    LookAt(f32, Height, f32),
    /// Along a heading and pitch, degrees.
    Angles {
        /// Heading, degrees.
        yaw: f32,
        /// Pitch, degrees.
        pitch: f32,
    },
}

/// Why a camera file is not acceptable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// The file could not be read.
    #[error("cannot read camera file {path}: {reason}")]
    Read {
        /// The path.
        path: String,
        /// The OS error.
        reason: String,
    },
    /// The file is too large.
    #[error("camera file {0} is larger than {MAX_CAMERA_FILE} bytes")]
    TooLarge(String),
    /// A statement is not understood.
    #[error("camera statement {line}: {message}")]
    Syntax {
        /// 1-based statement number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// No `position` statement.
    #[error("camera: no `position` statement")]
    NoPosition,
    /// Both `look-at` and `yaw`/`pitch`.
    #[error("camera: `look-at` and `yaw`/`pitch` exclude each other")]
    ConflictingAim,
}

fn syntax(line: usize, message: impl Into<String>) -> CameraError {
    CameraError::Syntax { line, message: message.into() }
}

impl CameraSpec {
    /// Read a camera file.
    pub fn load(path: &std::path::Path) -> Result<CameraSpec, CameraError> {
        use canopy_worlds::fsread::{ReadError, read_text};
        let text = read_text(path, MAX_CAMERA_FILE).map_err(|e| match e {
            ReadError::TooLarge { .. } => CameraError::TooLarge(path.display().to_string()),
            e => CameraError::Read { path: path.display().to_string(), reason: e.to_string() },
        })?;
        CameraSpec::parse(&text)
    }

    /// Parse camera statements, one per line or separated by `;`.
    pub fn parse(text: &str) -> Result<CameraSpec, CameraError> {
        let mut position = None;
        let mut look_at = None;
        let (mut yaw, mut pitch) = (None, None);
        let mut fov = None;
        for (n, raw) in text.split(['\n', ';']).enumerate() {
            let line = n + 1;
            let stmt = raw.split('#').next().unwrap_or("").trim();
            if stmt.is_empty() {
                continue;
            }
            let mut words = stmt.split_whitespace();
            let key = words.next().unwrap_or("");
            let args: Vec<&str> = words.collect();
            let want = |k: usize| -> Result<(), CameraError> {
                if args.len() == k { Ok(()) } else { Err(syntax(line, format!("`{key}` takes {k} number(s)"))) }
            };
            match key {
                "position" | "look-at" => {
                    want(3)?;
                    let p = (number(line, args[0])?, height(line, args[1])?, number(line, args[2])?);
                    let slot = if key == "position" { &mut position } else { &mut look_at };
                    if slot.replace(p).is_some() {
                        return Err(syntax(line, format!("`{key}` given twice")));
                    }
                }
                "yaw" | "pitch" | "fov" => {
                    want(1)?;
                    let v = number(line, args[0])?;
                    let (slot, lo, hi) = match key {
                        "yaw" => (&mut yaw, -3600.0, 3600.0),
                        "pitch" => (&mut pitch, -89.0, 89.0),
                        _ => (&mut fov, 5.0, 150.0),
                    };
                    if !(lo..=hi).contains(&v) {
                        return Err(syntax(line, format!("`{key}` {v} is outside {lo}..={hi}")));
                    }
                    if slot.replace(v).is_some() {
                        return Err(syntax(line, format!("`{key}` given twice")));
                    }
                }
                other => return Err(syntax(line, format!("unknown statement `{other}`"))),
            }
        }
        let position = position.ok_or(CameraError::NoPosition)?;
        let aim = match (look_at, yaw, pitch) {
            (Some(_), Some(_), _) | (Some(_), _, Some(_)) => return Err(CameraError::ConflictingAim),
            (Some((x, y, z)), None, None) => Aim::LookAt(x, y, z),
            (None, y, p) => Aim::Angles { yaw: y.unwrap_or(0.0), pitch: p.unwrap_or(0.0) },
        };
        Ok(CameraSpec { position, aim, fov_y: fov.unwrap_or(60.0) })
    }

    /// The camera, with heights above the terrain resolved by `ground(x, z)`.
    pub fn resolve(&self, ground: &dyn Fn(f32, f32) -> f32) -> Camera {
        let y = |x: f32, h: Height, z: f32| match h {
            Height::Absolute(v) => v,
            Height::AboveGround(v) => ground(x, z) + v,
        };
        let (x, h, z) = self.position;
        let position = Vec3::new(x, y(x, h, z), z);
        match self.aim {
            Aim::LookAt(tx, th, tz) => Camera::looking_at(position, Vec3::new(tx, y(tx, th, tz), tz), self.fov_y),
            Aim::Angles { yaw, pitch } => {
                Camera { position, yaw: yaw.to_radians(), pitch: clamp_pitch(pitch.to_radians()), fov_y: self.fov_y }
            }
        }
    }
}

fn number(line: usize, s: &str) -> Result<f32, CameraError> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v.abs() <= MAX_COORDINATE => Ok(v),
        _ => Err(syntax(line, format!("`{s}` is not a number within ±{MAX_COORDINATE}"))),
    }
}

fn height(line: usize, s: &str) -> Result<Height, CameraError> {
    match s.strip_prefix('~') {
        Some(rest) => Ok(Height::AboveGround(if rest.is_empty() { 0.0 } else { number(line, rest)? })),
        None => Ok(Height::Absolute(number(line, s)?)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_files_and_inline_statements() {
        let spec = CameraSpec::parse("position 1 ~5 -3 # eye\nlook-at 1 ~0 10\nfov 45\n").unwrap();
        assert_eq!(spec.position, (1.0, Height::AboveGround(5.0), -3.0));
        assert_eq!(spec.aim, Aim::LookAt(1.0, Height::AboveGround(0.0), 10.0));
        assert_eq!(spec.fov_y, 45.0);
        let cam = spec.resolve(&|_, _| 100.0);
        assert_eq!(cam.position, Vec3::new(1.0, 105.0, -3.0));
        assert!(cam.yaw.abs() < 1e-6, "looks along +z");
        assert!(cam.pitch < 0.0, "looks down");
        let inline = CameraSpec::parse("position 0 20 0; yaw 90; pitch -10").unwrap().resolve(&|_, _| 0.0);
        assert!((inline.forward() - Vec3::new(0.9848, -0.1736, 0.0)).length() < 1e-3, "{:?}", inline.forward());
    }

    #[test]
    fn rejects_bad_files_with_reasons() {
        let err = |t: &str| CameraSpec::parse(t).unwrap_err();
        assert_eq!(err("look-at 0 0 1"), CameraError::NoPosition);
        assert!(matches!(err("position 0 0"), CameraError::Syntax { line: 1, .. }));
        assert!(matches!(err("position 0 0 0\nposition 1 1 1"), CameraError::Syntax { line: 2, .. }));
        assert!(matches!(err("position 0 nan 0"), CameraError::Syntax { .. }));
        assert!(matches!(err("position 0 1e9 0"), CameraError::Syntax { .. }));
        assert!(matches!(err("position 0 0 0\nfov 300"), CameraError::Syntax { .. }));
        assert!(matches!(err("position 0 0 0\nzoom 2"), CameraError::Syntax { .. }));
        assert_eq!(err("position 0 0 0\nlook-at 1 1 1\nyaw 3"), CameraError::ConflictingAim);
        let missing = CameraSpec::load(std::path::Path::new("/nonexistent/camera.txt")).unwrap_err();
        assert!(matches!(missing, CameraError::Read { .. }));
    }

    #[test]
    fn frustum_culls_spheres_behind_and_beside() {
        let cam = Camera { position: Vec3::ZERO, yaw: 0.0, pitch: 0.0, fov_y: 60.0 };
        let f = Frustum::from_matrix(cam.view_projection(1.0, 0.1));
        assert!(f.sphere_visible(Vec3::new(0.0, 0.0, 50.0), 1.0), "ahead");
        assert!(!f.sphere_visible(Vec3::new(0.0, 0.0, -50.0), 1.0), "behind");
        assert!(!f.sphere_visible(Vec3::new(100.0, 0.0, 50.0), 1.0), "far to the side");
        assert!(f.sphere_visible(Vec3::new(29.5, 0.0, 50.0), 1.0), "touching a 60° frustum (tan 30° · 50 ≈ 28.9, + r)");
        assert!(!f.sphere_visible(Vec3::new(31.0, 0.0, 50.0), 1.0), "just outside");
        assert!(f.sphere_visible(Vec3::new(0.0, 0.0, 1e5), 1.0), "no far plane");
    }
}
