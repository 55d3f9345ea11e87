//! The page's camera: flying as the native walk flies (W/A/S/D along the view and its right, Q/E or C/Space down
//! and up, Shift four times faster, never below half a metre over the ground), turned by the mouse or the arrow
//! keys, or led along a scripted walk ([`Walk`]: what a test drives through `window.canopyWalk`).

/// Which movement keys are down.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Keys {
    /// W.
    pub forward: bool,
    /// S.
    pub back: bool,
    /// A.
    pub left: bool,
    /// D.
    pub right: bool,
    /// E or Space.
    pub up: bool,
    /// Q or C.
    pub down: bool,
    /// Shift.
    pub fast: bool,
    /// Arrow left.
    pub turn_left: bool,
    /// Arrow right.
    pub turn_right: bool,
    /// Arrow up.
    pub look_up: bool,
    /// Arrow down.
    pub look_down: bool,
}

impl Keys {
    /// Set the key named by a `KeyboardEvent.code` (`"KeyW"`, `"ShiftLeft"`, ...); `false` for a key that does
    /// not move the camera.
    pub fn set(&mut self, code: &str, down: bool) -> bool {
        let k = match code {
            "KeyW" => &mut self.forward,
            "KeyS" => &mut self.back,
            "KeyA" => &mut self.left,
            "KeyD" => &mut self.right,
            "KeyE" | "Space" => &mut self.up,
            "KeyQ" | "KeyC" => &mut self.down,
            "ShiftLeft" | "ShiftRight" => &mut self.fast,
            "ArrowLeft" => &mut self.turn_left,
            "ArrowRight" => &mut self.turn_right,
            "ArrowUp" => &mut self.look_up,
            "ArrowDown" => &mut self.look_down,
            _ => return false,
        };
        *k = down;
        true
    }

    /// Whether any key that moves or turns is down.
    pub fn any(&self) -> bool {
        *self != Keys { fast: self.fast, ..Keys::default() }
    }
}

/// A scripted walk: waypoints on (x, z) taken in order at a speed, the camera turning to face each leg.
#[derive(Clone, Debug, PartialEq)]
pub struct Walk {
    points: Vec<[f32; 2]>,
    next: usize,
    speed: f32,
}

impl Walk {
    /// A walk through `points` at `speed` metres a second; `None` if there is no point or a number is not finite
    /// or the speed not positive.
    pub fn new(points: Vec<[f32; 2]>, speed: f32) -> Option<Walk> {
        let finite = points.iter().flatten().all(|v| v.is_finite());
        (!points.is_empty() && finite && speed.is_finite() && speed > 0.0).then_some(Walk { points, next: 0, speed })
    }

    /// Whether every waypoint has been reached.
    pub fn done(&self) -> bool {
        self.next >= self.points.len()
    }
}

/// Turn speed of the arrow keys, radians a second (the native walk's).
const KEY_TURN: f32 = 1.2;
/// Radians a pixel of mouse movement.
pub const MOUSE_TURN: f32 = 0.0025;
/// Lowest eye height over the ground, metres.
const MIN_CLEARANCE: f32 = 0.5;
/// Highest pitch, radians (89°).
const MAX_PITCH: f32 = 1.553_343;

/// See the module docs.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// The eye, x, y (up), z, metres.
    pub position: [f32; 3],
    /// Heading, radians: 0 looks along +z, π/2 along +x.
    pub yaw: f32,
    /// Pitch, radians, positive looks up.
    pub pitch: f32,
    /// Speed, metres a second (Shift: four times).
    pub speed: f32,
    /// Whether it has been placed at the first viewpoint yet.
    pub placed: bool,
    walk: Option<Walk>,
}

impl Default for Camera {
    fn default() -> Camera {
        Camera { position: [0.0, 30.0, 0.0], yaw: 0.0, pitch: -0.2, speed: 15.0, placed: false, walk: None }
    }
}

impl Camera {
    /// The horizontal unit view direction on (x, z): `(sin yaw, cos yaw)`.
    pub fn heading(&self) -> [f32; 2] {
        let (s, c) = self.yaw.sin_cos();
        [s, c]
    }

    /// The horizontal unit right vector on (x, z): `(−cos yaw, sin yaw)` (the renderer's `Camera::right`).
    pub fn right(&self) -> [f32; 2] {
        let (s, c) = self.yaw.sin_cos();
        [-c, s]
    }

    /// Turn by `right` radians towards the right vector and `up` radians of pitch.
    pub fn turn(&mut self, right: f32, up: f32) {
        // The heading's derivative in yaw is minus the right vector: turning right lowers the yaw.
        self.yaw = (self.yaw - right).rem_euclid(std::f32::consts::TAU);
        self.pitch = (self.pitch + up).clamp(-MAX_PITCH, MAX_PITCH);
    }

    /// Place the camera at `(x, z)`, `altitude` metres over the ground there, keeping its heading (a scripted walk
    /// is stopped).
    pub fn teleport(&mut self, x: f32, z: f32, altitude: f32, height: &dyn Fn(f32, f32) -> f32) {
        self.position = [x, height(x, z) + altitude.max(MIN_CLEARANCE), z];
        self.walk = None;
        self.placed = true;
    }

    /// Follow `walk` from where the camera is.
    pub fn walk(&mut self, walk: Walk) {
        self.walk = Some(walk);
    }

    /// Whether a scripted walk is under way.
    pub fn walking(&self) -> bool {
        self.walk.as_ref().is_some_and(|w| !w.done())
    }

    /// Move for `dt` seconds with `keys` down (keys stop a scripted walk); returns the velocity on (x, z).
    pub fn step(&mut self, keys: &Keys, dt: f32, height: &dyn Fn(f32, f32) -> f32) -> [f32; 2] {
        let dt = dt.clamp(0.0, 0.25);
        let axis = |a: bool, b: bool| f32::from(u8::from(a)) - f32::from(u8::from(b));
        self.turn(
            KEY_TURN * dt * axis(keys.turn_right, keys.turn_left),
            KEY_TURN * dt * axis(keys.look_up, keys.look_down),
        );
        if keys.any() {
            self.walk = None;
        }
        let velocity = match &mut self.walk {
            Some(w) if !w.done() => {
                let v = Self::lead(&mut self.position, &mut self.yaw, w, dt);
                if w.done() {
                    self.walk = None;
                }
                v
            }
            _ => self.fly(keys, dt),
        };
        let ground = height(self.position[0], self.position[2]);
        self.position[1] = self.position[1].max(ground + MIN_CLEARANCE);
        velocity
    }

    fn fly(&mut self, keys: &Keys, dt: f32) -> [f32; 2] {
        let axis = |a: bool, b: bool| f32::from(u8::from(a)) - f32::from(u8::from(b));
        let (sp, cp) = self.pitch.sin_cos();
        let [hx, hz] = self.heading();
        let [rx, rz] = self.right();
        let (f, r, u) = (axis(keys.forward, keys.back), axis(keys.right, keys.left), axis(keys.up, keys.down));
        let v = [f * cp * hx + r * rx, f * sp + u, f * cp * hz + r * rz];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if len == 0.0 {
            return [0.0, 0.0];
        }
        let speed = if keys.fast { self.speed * 4.0 } else { self.speed };
        let k = speed / len;
        for (p, d) in self.position.iter_mut().zip(v) {
            *p += d * k * dt;
        }
        [v[0] * k, v[2] * k]
    }

    /// Advance along a walk by `dt`, facing the current leg.
    fn lead(position: &mut [f32; 3], yaw: &mut f32, w: &mut Walk, dt: f32) -> [f32; 2] {
        let mut budget = w.speed * dt;
        let start = [position[0], position[2]];
        while budget > 0.0 && !w.done() {
            let target = w.points[w.next];
            let d = [target[0] - position[0], target[1] - position[2]];
            let len = (d[0] * d[0] + d[1] * d[1]).sqrt();
            if len > 1e-3 {
                *yaw = d[0].atan2(d[1]).rem_euclid(std::f32::consts::TAU);
            }
            if len <= budget {
                position[0] = target[0];
                position[2] = target[1];
                budget -= len;
                w.next += 1;
            } else {
                position[0] += d[0] / len * budget;
                position[2] += d[1] / len * budget;
                budget = 0.0;
            }
        }
        if dt > 0.0 { [(position[0] - start[0]) / dt, (position[2] - start[1]) / dt] } else { [0.0, 0.0] }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(_: f32, _: f32) -> f32 {
        0.0
    }

    #[test]
    fn w_moves_along_the_heading_d_along_the_right_and_shift_is_four_times_faster() {
        let mut c = Camera { pitch: 0.0, position: [0.0, 10.0, 0.0], ..Camera::default() };
        let keys = Keys { forward: true, ..Keys::default() };
        let v = c.step(&keys, 0.1, &flat);
        assert!((c.position[2] - 1.5).abs() < 1e-5 && c.position[0].abs() < 1e-5, "{:?}", c.position);
        assert!((v[1] - 15.0).abs() < 1e-4);
        let keys = Keys { right: true, fast: true, ..Keys::default() };
        c.step(&keys, 0.1, &flat);
        assert!((c.position[0] + 6.0).abs() < 1e-4, "right of +z is −x: {:?}", c.position);
        // Down stops half a metre over the ground.
        let keys = Keys { down: true, ..Keys::default() };
        for _ in 0..20 {
            c.step(&keys, 0.25, &|_, _| 2.0);
        }
        assert_eq!(c.position[1], 2.5);
    }

    #[test]
    fn turning_right_turns_the_heading_towards_the_right_vector() {
        let mut c = Camera::default();
        let right = c.right();
        c.turn(0.1, 0.0);
        let h = c.heading();
        assert!(h[0] * right[0] + h[1] * right[1] > 0.09, "{h:?} {right:?}");
        c.turn(0.0, 10.0);
        assert!(c.pitch < 1.56);
        assert!(Keys::default().set("ArrowLeft", true) && !Keys::default().set("KeyZ", true));
    }

    #[test]
    fn a_walk_visits_its_points_in_order_and_keys_take_over() {
        let mut c = Camera { position: [0.0, 10.0, 0.0], ..Camera::default() };
        c.walk(Walk::new(vec![[0.0, 10.0], [10.0, 10.0]], 20.0).unwrap());
        assert!(c.walking());
        let v = c.step(&Keys::default(), 0.25, &flat);
        assert_eq!([c.position[0], c.position[2]], [0.0, 5.0]);
        assert!((v[1] - 20.0).abs() < 1e-4 && c.yaw.abs() < 1e-6);
        // A long frame counts a quarter of a second at most.
        c.step(&Keys::default(), 2.0, &flat);
        c.step(&Keys::default(), 0.0, &flat);
        assert_eq!([c.position[0], c.position[2]], [0.0, 10.0]);
        c.step(&Keys::default(), 0.25, &flat);
        assert_eq!([c.position[0], c.position[2]], [5.0, 10.0]);
        assert!((c.yaw - std::f32::consts::FRAC_PI_2).abs() < 1e-5, "facing +x: {}", c.yaw);
        c.step(&Keys::default(), 0.25, &flat);
        assert!(!c.walking());
        assert_eq!([c.position[0], c.position[2]], [10.0, 10.0]);
        c.walk(Walk::new(vec![[100.0, 100.0]], 1.0).unwrap());
        c.step(&Keys { forward: true, ..Keys::default() }, 0.1, &flat);
        assert!(!c.walking(), "a key stops the walk");
        assert!(Walk::new(vec![], 1.0).is_none() && Walk::new(vec![[f32::NAN, 0.0]], 1.0).is_none());
        c.teleport(7.0, 8.0, 20.0, &|_, _| 3.0);
        assert_eq!(c.position, [7.0, 23.0, 8.0]);
    }
}
