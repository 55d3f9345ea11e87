//! Level-of-detail selection by projected size (seed 001 §5), with hysteresis and dithered cross-fades. Pure: no
//! GPU, no clock (time arrives as fade progress).
//!
//! An instance's projected size is the height in pixels of its bounding sphere's diameter on screen. Levels are
//! [`Level::Detail`] `0..=mid_levels` (0 near, the rest mid: one level coarser per halving of the size below
//! [`LodConfig::near_px`]) and [`Level::Far`] below [`LodConfig::far_px`]. A level changes only when the size
//! leaves the current level's range by more than the hysteresis fraction, so walking along a threshold does not
//! flicker. A change cross-fades: the new level is drawn where a screen-space Bayer threshold is below the fade
//! progress and the old level where it is not — complementary masks, so no pixel is drawn twice or left empty.

use super::ConfigError;
use super::volume::FAR_LEVELS;

/// Distance bands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Band {
    /// Full amplified geometry.
    Near,
    /// LOD substitutes.
    Mid,
    /// Hypertree volumes.
    Far,
}

/// A level of detail.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Level {
    /// Amplified geometry at this detail (0 = full; each step selects coarser LOD substitutes).
    Detail(u8),
    /// The species' hypertree volume.
    Far,
}

impl Level {
    /// The band of the level.
    pub fn band(self) -> Band {
        match self {
            Level::Detail(0) => Band::Near,
            Level::Detail(_) => Band::Mid,
            Level::Far => Band::Far,
        }
    }

    /// 0 for full detail, increasing toward the far field.
    pub fn rank(self) -> u8 {
        match self {
            Level::Detail(d) => d,
            Level::Far => u8::MAX,
        }
    }
}

/// Thresholds of the bands (all in pixels of projected height), hysteresis and fade time.
#[derive(Clone, Debug, PartialEq)]
pub struct LodConfig {
    /// At or above this size an instance is drawn at full detail.
    pub near_px: f32,
    /// Below this size an instance is drawn as a hypertree volume.
    pub far_px: f32,
    /// Mid-band detail levels `1..=mid_levels` (the species' LOD substitutes; 0 makes the mid band empty).
    pub mid_levels: u8,
    /// Below this size an instance is not drawn.
    pub cull_px: f32,
    /// Far instances below this size use the halved volume resolution, below half of it a quarter of the full
    /// resolution, below a quarter of it an eighth (as `far_resolutions` allows).
    pub low_res_px: f32,
    /// Resolutions far instances are drawn at (2: full and halved; 4: down to an eighth).
    pub far_resolutions: u8,
    /// A level changes only when the size leaves its range by this fraction (0.15 = ±15 %).
    pub hysteresis: f32,
    /// Duration of a cross-fade, seconds (0 switches at once).
    pub fade_seconds: f32,
}

impl Default for LodConfig {
    fn default() -> Self {
        LodConfig {
            near_px: 700.0,
            far_px: 90.0,
            mid_levels: 3,
            cull_px: 1.0,
            low_res_px: 24.0,
            far_resolutions: 4,
            hysteresis: 0.15,
            fade_seconds: 0.4,
        }
    }
}

impl LodConfig {
    /// Check the numbers.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let pos = |v: f32| v.is_finite() && v >= 0.0;
        let checks = [
            (pos(self.near_px) && self.near_px <= 1e7, "near threshold"),
            (pos(self.far_px) && self.far_px <= self.near_px, "far threshold (at most the near threshold)"),
            (pos(self.cull_px) && self.cull_px <= self.far_px.max(1.0), "cull threshold"),
            (pos(self.low_res_px), "low-resolution threshold"),
            ((2..=FAR_LEVELS as u8).contains(&self.far_resolutions), "far resolutions"),
            (self.mid_levels <= 16, "mid-band levels"),
            ((0.0..0.9).contains(&self.hysteresis), "hysteresis"),
            (pos(self.fade_seconds) && self.fade_seconds <= 60.0, "fade time"),
        ];
        match checks.iter().find(|c| !c.0) {
            Some((_, what)) => Err(ConfigError::Range(what)),
            None => Ok(()),
        }
    }

    /// The level for a projected size, without hysteresis.
    pub fn ideal(&self, size_px: f32) -> Level {
        if size_px >= self.near_px {
            return Level::Detail(0);
        }
        if size_px < self.far_px || self.mid_levels == 0 {
            return if size_px >= self.far_px { Level::Detail(0) } else { Level::Far };
        }
        // One level per halving below the near threshold: [near/2, near) is detail 1, [near/4, near/2) detail 2…
        let halvings = (self.near_px / size_px.max(f32::MIN_POSITIVE)).log2().ceil() as i64;
        Level::Detail(halvings.clamp(1, i64::from(self.mid_levels)) as u8)
    }

    /// The level for a projected size given the current level: keeps `current` while the size is within the
    /// hysteresis margin of its range.
    pub fn select(&self, current: Option<Level>, size_px: f32) -> Level {
        let ideal = self.ideal(size_px);
        let Some(cur) = current else { return ideal };
        if ideal == cur {
            return cur;
        }
        // Finer than ideal: keep it while the size is within the margin above the coarser threshold, and vice
        // versa.
        let keep = if cur.rank() < ideal.rank() {
            self.ideal(size_px * (1.0 + self.hysteresis)).rank() <= cur.rank()
        } else {
            self.ideal(size_px * (1.0 - self.hysteresis)).rank() >= cur.rank()
        };
        if keep { cur } else { ideal }
    }
}

/// What one instance draws while levels change.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct InstanceLod {
    /// The level drawn (fading in while `fade < 1`).
    pub shown: Option<Level>,
    /// The level fading out.
    pub old: Option<Level>,
    /// Fade progress of `shown`, 0..=1.
    pub fade: f32,
}

/// One draw of an instance: a level and its screen-door mask.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct LodDraw {
    /// The level.
    pub level: Level,
    /// The dither mask for the shaders: `m ≥ 0` keeps pixels whose Bayer threshold is below `m` (1 keeps all);
    /// `m < 0` keeps those at or above `−m` (the complement of `+(−m)`).
    pub mask: f32,
}

impl InstanceLod {
    /// Advance by `progress` of a fade (`dt / fade_seconds`; ≥ 1 finishes any fade) toward `wanted`, drawing only
    /// levels for which `ready` holds. When `wanted` is not ready the shown level stays; when nothing is shown
    /// yet, the nearest ready level (coarser first) stands in.
    pub(crate) fn step(&mut self, wanted: Level, progress: f32, ready: &dyn Fn(Level) -> bool, others: &[Level]) {
        if let Some(s) = self.shown
            && !ready(s)
        {
            self.shown = None;
            self.fade = 1.0;
        }
        if let Some(o) = self.old
            && !ready(o)
        {
            self.old = None;
        }
        if self.fade < 1.0 {
            self.fade = (self.fade + progress).min(1.0);
        }
        if self.fade >= 1.0 {
            self.old = None;
        }
        if self.shown == Some(wanted) || self.fade < 1.0 {
            return;
        }
        let next = if ready(wanted) {
            Some(wanted)
        } else if self.shown.is_none() {
            // Coarser stand-ins first (cheaper, and what a level change toward them would show anyway).
            let mut cands: Vec<Level> = others.iter().copied().filter(|l| *l != wanted && ready(*l)).collect();
            cands.sort_by_key(|l| (l.rank() < wanted.rank(), l.rank().abs_diff(wanted.rank())));
            cands.first().copied()
        } else {
            None
        };
        if let Some(n) = next {
            self.old = self.shown;
            self.shown = Some(n);
            self.fade = if progress >= 1.0 { 1.0 } else { progress.max(0.0) };
            if self.fade >= 1.0 {
                self.old = None;
            }
        }
    }

    /// The draws of this instance (at most two).
    pub(crate) fn draws(&self) -> impl Iterator<Item = LodDraw> {
        let shown = self.shown.map(|level| LodDraw { level, mask: self.fade.clamp(0.0, 1.0) });
        let old = match (self.old, self.fade < 1.0) {
            (Some(level), true) => Some(LodDraw { level, mask: -self.fade.clamp(0.0, 1.0) }),
            _ => None,
        };
        shown.into_iter().chain(old)
    }
}

/// Projected height in pixels of a sphere of `radius` at `distance`, for a viewport `height_px` tall with
/// `tan(fov_y / 2) = tan_half`.
pub(crate) fn projected_size(radius: f32, distance: f32, tan_half: f32, height_px: f32) -> f32 {
    if distance <= radius {
        return f32::MAX;
    }
    radius * height_px / (distance * tan_half)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 4×4 Bayer threshold of a pixel, in `[0, 1)` (the same table as the shaders').
    fn bayer4(x: u32, y: u32) -> f32 {
        const M: [u8; 16] = [0, 8, 2, 10, 12, 4, 14, 6, 3, 11, 1, 9, 15, 7, 13, 5];
        (f32::from(M[((y & 3) * 4 + (x & 3)) as usize]) + 0.5) / 16.0
    }

    /// Whether a mask keeps a pixel with Bayer threshold `b` (the shaders' `dither_keeps`, see [`LodDraw::mask`]).
    fn mask_keeps(mask: f32, b: f32) -> bool {
        if mask >= 0.0 { b < mask } else { b >= -mask }
    }

    fn cfg() -> LodConfig {
        LodConfig { near_px: 400.0, far_px: 50.0, mid_levels: 3, ..LodConfig::default() }
    }

    #[test]
    fn ideal_levels_follow_the_thresholds() {
        let c = cfg();
        let check = |size: f32, want: Level| assert_eq!(c.ideal(size), want, "size {size}");
        check(1000.0, Level::Detail(0));
        check(400.0, Level::Detail(0));
        check(399.0, Level::Detail(1));
        check(200.0, Level::Detail(1));
        check(199.0, Level::Detail(2));
        check(100.0, Level::Detail(2));
        check(99.0, Level::Detail(3));
        check(50.0, Level::Detail(3));
        check(49.9, Level::Far);
        check(0.0, Level::Far);
        let none = LodConfig { mid_levels: 0, ..cfg() };
        assert_eq!(none.ideal(200.0), Level::Detail(0));
        assert_eq!(none.ideal(10.0), Level::Far);
        assert_eq!(Level::Detail(0).band(), Band::Near);
        assert_eq!(Level::Detail(2).band(), Band::Mid);
        assert_eq!(Level::Far.band(), Band::Far);
    }

    #[test]
    fn hysteresis_keeps_a_level_near_its_border() {
        let c = cfg();
        // Detail 1 above 200 px: shrinking to 180 px (within 15 %) keeps it, to 170 px does not.
        assert_eq!(c.select(Some(Level::Detail(1)), 180.0), Level::Detail(1));
        assert_eq!(c.select(Some(Level::Detail(1)), 170.0), Level::Detail(2));
        // Detail 2 below 200 px: growing to 220 px keeps it, to 240 px does not.
        assert_eq!(c.select(Some(Level::Detail(2)), 220.0), Level::Detail(2));
        assert_eq!(c.select(Some(Level::Detail(2)), 240.0), Level::Detail(1));
        // Far below 50 px.
        assert_eq!(c.select(Some(Level::Far), 55.0), Level::Far);
        assert_eq!(c.select(Some(Level::Far), 60.0), Level::Detail(3));
        assert_eq!(c.select(Some(Level::Detail(3)), 45.0), Level::Detail(3));
        assert_eq!(c.select(Some(Level::Detail(3)), 40.0), Level::Far);
        // A jump across several levels is not held back.
        assert_eq!(c.select(Some(Level::Detail(0)), 10.0), Level::Far);
        assert_eq!(c.select(None, 180.0), Level::Detail(2));
        // Oscillating around a threshold never changes the level.
        let mut cur = c.select(None, 210.0);
        for i in 0..100 {
            let size = 200.0 + if i % 2 == 0 { 12.0 } else { -12.0 };
            cur = c.select(Some(cur), size);
            assert_eq!(cur, Level::Detail(1));
        }
    }

    #[test]
    fn cross_fade_masks_are_complementary() {
        let mut lod = InstanceLod::default();
        let all = |_: Level| true;
        lod.step(Level::Detail(2), 1.0, &all, &[]);
        assert_eq!(lod.draws().collect::<Vec<_>>(), vec![LodDraw { level: Level::Detail(2), mask: 1.0 }]);
        lod.step(Level::Detail(1), 0.25, &all, &[]);
        let draws: Vec<_> = lod.draws().collect();
        assert_eq!(draws.len(), 2);
        assert_eq!(draws[0].level, Level::Detail(1));
        assert_eq!(draws[1].level, Level::Detail(2));
        // Every pixel of a 4×4 block is drawn by exactly one of the two.
        for y in 0..4 {
            for x in 0..4 {
                let b = bayer4(x, y);
                assert!(mask_keeps(draws[0].mask, b) ^ mask_keeps(draws[1].mask, b), "pixel {x},{y}");
            }
        }
        let kept = (0..16).filter(|i| mask_keeps(draws[0].mask, bayer4(i % 4, i / 4))).count();
        assert_eq!(kept, 4, "a quarter of the way, a quarter of the pixels");
        // A change requested mid-fade waits for the fade to end.
        lod.step(Level::Far, 0.25, &all, &[]);
        assert_eq!(lod.shown, Some(Level::Detail(1)));
        // The fade ends within this step and the next one starts with the rest of the step's progress.
        lod.step(Level::Far, 0.5, &all, &[]);
        assert_eq!((lod.shown, lod.old, lod.fade), (Some(Level::Far), Some(Level::Detail(1)), 0.5));
        lod.step(Level::Far, 0.5, &all, &[]);
        assert_eq!((lod.shown, lod.old, lod.fade), (Some(Level::Far), None, 1.0));
        assert_eq!(lod.draws().count(), 1);
    }

    #[test]
    fn missing_geometry_never_blocks_and_stand_ins_are_coarser_first() {
        let mut lod = InstanceLod::default();
        let only_far = |l: Level| l == Level::Far;
        let levels = [Level::Detail(0), Level::Detail(1), Level::Detail(3), Level::Far];
        lod.step(Level::Detail(1), 1.0, &only_far, &levels);
        assert_eq!(lod.shown, Some(Level::Far), "the far volume stands in");
        let coarse = |l: Level| l == Level::Detail(3) || l == Level::Detail(0);
        let mut fresh = InstanceLod::default();
        fresh.step(Level::Detail(1), 1.0, &coarse, &levels);
        assert_eq!(fresh.shown, Some(Level::Detail(3)), "coarser before finer");
        // Once something is shown, a missing wanted level keeps it.
        lod.step(Level::Detail(1), 1.0, &only_far, &levels);
        assert_eq!(lod.shown, Some(Level::Far));
        // Evicted geometry is dropped rather than drawn.
        lod.step(Level::Detail(1), 1.0, &|_| false, &levels);
        assert_eq!(lod.shown, None);
        assert_eq!(lod.draws().count(), 0);
    }

    #[test]
    fn projected_size_is_the_sphere_diameter_on_screen() {
        // A 10 m radius at 100 m with a 90° field of view on a 1000 px viewport: 20 m over 200 m of view = 100 px.
        assert!((projected_size(10.0, 100.0, 1.0, 1000.0) - 100.0).abs() < 1e-3);
        assert_eq!(projected_size(10.0, 5.0, 1.0, 1000.0), f32::MAX);
    }

    #[test]
    fn config_validation_rejects_nonsense() {
        assert!(LodConfig::default().validate().is_ok());
        assert!(LodConfig { far_px: 900.0, near_px: 100.0, ..cfg() }.validate().is_err());
        assert!(LodConfig { hysteresis: f32::NAN, ..cfg() }.validate().is_err());
        assert!(LodConfig { near_px: f32::INFINITY, ..cfg() }.validate().is_err());
    }
}
