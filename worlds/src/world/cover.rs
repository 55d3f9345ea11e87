//! What covers the ground where no instance is drawn: the `scatter` rules read as a function of height and slope
//! (trees, low plants, bare ground) and the snow line above the highest of them. The renderer colours the terrain
//! with it, so the land reads from the air as the world describes it: forest floor under the conifers, meadow
//! where only weeds and bushes grow, rock and scree past the tree line, snow on the peaks above.
//!
//! It reads the rules' ramps only (no darts, no `avoid`): the expected share of ground each kind of plant takes,
//! not where a plant stands, so it is smooth, cheap and the same on every machine.

use super::{Ramp, SlopeRamp, World};

/// A rule's plants count as trees when their `height` parameter averages at least this many metres.
pub const TREE_HEIGHT: f64 = 4.0;
/// Snow starts this many metres above the highest altitude any rule keeps plants at …
pub const SNOW_ABOVE: f32 = 150.0;
/// … and lies everywhere (on ground not too steep to hold it) this many metres higher.
pub const SNOW_FULL: f32 = 200.0;

/// One rule as the cover reads it.
#[derive(Clone, Debug, PartialEq)]
struct CoverRule {
    density: f32,
    altitude: Ramp,
    slope: SlopeRamp,
    tree: bool,
}

/// The ground's cover as a function of height and slope (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct GroundCover {
    rules: Vec<CoverRule>,
    snow_line: Option<f32>,
}

/// The cover at one place: each share in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cover {
    /// How much of the ground trees take: `1 − Π (1 − keep)` over the tree rules.
    pub trees: f32,
    /// How much low plants (bushes, weeds, every rule not of trees) take, the same way.
    pub plants: f32,
    /// Snow: 0 below the snow line, 1 from [`SNOW_FULL`] metres above it.
    pub snow: f32,
}

impl GroundCover {
    /// The cover of a world's rules. A world whose rules all stop at some altitude has a snow line
    /// [`SNOW_ABOVE`] metres above the highest; one with a rule that grows however high has none.
    pub fn of_world(world: &World) -> GroundCover {
        let heights = super::far::rule_heights(world);
        let rules: Vec<CoverRule> = world
            .rules
            .iter()
            .zip(heights)
            .map(|(r, h)| CoverRule {
                density: r.density,
                altitude: r.altitude,
                slope: r.slope,
                tree: h.is_some_and(|h| h >= TREE_HEIGHT),
            })
            .collect();
        let top = rules.iter().map(|r| r.altitude.d).fold(f32::NEG_INFINITY, f32::max);
        let snow_line = (!rules.is_empty() && top.is_finite()).then_some(top + SNOW_ABOVE);
        GroundCover { rules, snow_line }
    }

    /// No plants and no snow: bare ground everywhere (a world without rules).
    pub fn bare() -> GroundCover {
        GroundCover { rules: Vec::new(), snow_line: None }
    }

    /// Where snow starts, metres, if the world has a snow line.
    pub fn snow_line(&self) -> Option<f32> {
        self.snow_line
    }

    /// The cover on ground of `height` whose squared gradient is `g2` (as [`World::height_and_gradient2`] gives).
    pub fn at(&self, height: f32, g2: f64) -> Cover {
        let (mut bare_of_trees, mut bare_of_plants) = (1.0f32, 1.0f32);
        for r in &self.rules {
            let keep = (r.density * r.altitude.at(height) * r.slope.at(g2)).clamp(0.0, 1.0);
            if r.tree {
                bare_of_trees *= 1.0 - keep;
            } else {
                bare_of_plants *= 1.0 - keep;
            }
        }
        let snow = self.snow_line.map_or(0.0, |line| ((height - line) / SNOW_FULL).clamp(0.0, 1.0));
        Cover { trees: 1.0 - bare_of_trees, plants: 1.0 - bare_of_plants, snow }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(cover: &GroundCover, h: f32) -> Cover {
        cover.at(h, 0.0)
    }

    #[test]
    fn the_highlands_cover_follows_their_rules_up_to_the_snow() {
        let world = World::embedded("highlands").expect("embedded");
        let cover = GroundCover::of_world(&world);
        // The weeds stop at 1,350 m, the highest rule's end: snow from 1,500 m, full at 1,700 m.
        assert_eq!(cover.snow_line(), Some(1_350.0 + SNOW_ABOVE));
        // Conifer forest at 900 m: trees take nearly all the ground, weeds some of it, no snow.
        let forest = flat(&cover, 900.0);
        assert!(forest.trees > 0.99 && forest.plants > 0.5 && forest.snow == 0.0, "{forest:?}");
        // Broadleaf valleys at 200 m: trees.
        assert!(flat(&cover, 200.0).trees > 0.99);
        // Past the tree line (1,280 m), weeds thinning out: no trees, some plants.
        let above = flat(&cover, 1_300.0);
        assert!(above.trees == 0.0 && above.plants > 0.0 && above.plants < 0.8, "{above:?}");
        // Bare rock at 1,400 m, half snow at 1,600 m, all snow at 1,800 m.
        assert_eq!(flat(&cover, 1_400.0), Cover { trees: 0.0, plants: 0.0, snow: 0.0 });
        assert_eq!(flat(&cover, 1_600.0).snow, 0.5);
        assert_eq!(flat(&cover, 1_800.0).snow, 1.0);
        // A 50° slope at 900 m is past the conifers' slope ramp (.. 35 45): no trees there.
        let steep = libm::pow(libm::tan(50f64.to_radians()), 2.0);
        assert_eq!(cover.at(900.0, steep).trees, 0.0);
    }

    #[test]
    fn a_world_whose_trees_grow_however_high_has_no_snow() {
        let world = World::default_world();
        let cover = GroundCover::of_world(&world);
        assert_eq!(cover.snow_line(), None);
        // The default world's conifers (altitude 100 140 ..) take the hills, its broadleaves the low ground.
        assert!(flat(&cover, 10_000.0).trees > 0.99 && flat(&cover, 10_000.0).snow == 0.0);
        assert!(flat(&cover, 60.0).trees > 0.99);
        assert_eq!(GroundCover::bare().at(500.0, 0.0), Cover { trees: 0.0, plants: 0.0, snow: 0.0 });
    }
}
