//! Leaf cards (issue 33, item 3): each flat leaf of a species drawn as one quad in its plane, from its petiole to
//! its tip, whose silhouette the fragment shader cuts procedurally (`segment.wgsl` `leaf_half_width`): a blade
//! widest where the species' own leaf is widest, toothed along its margins, on a short stalk, with a midrib and
//! side veins. No art is read: the shape is a function of three numbers the card's vertices carry.
//!
//! The card keeps the leaf's area: its width is chosen so that the silhouette covers what the species' polygon
//! covered, so a crown passes as much light, and weighs as much in the far field's bake, as before. A leaf that is
//! not flat (a curved strip) or has no area keeps its polygon mesh.
//!
//! A card vertex says where it is on the card in its colour's alpha byte (the rest of the vertex is as for any
//! mesh): bit 0 is `u` (0 at the petiole, 1 at the tip), bit 1 the side (`v` −1 or +1), bits 2..=6 where the blade
//! is widest ([`widest`]), bit 7 clear. Every other vertex has alpha 255 (bit 7 set): not a card.

use std::sync::OnceLock;

use canopy_protocol::LeafTopology;
use canopy_worlds::primitive::{Primitive, PrimitiveStream, Shape};
use glam::Vec3;

/// The alpha byte of a vertex that is not on a card.
pub(crate) const NOT_A_CARD: u8 = 255;

/// Levels of the widest point's position along the blade (5 bits).
const WIDEST_LEVELS: u8 = 31;
/// The widest point's range along the blade, from the petiole (0) to the tip (1).
const WIDEST_MIN: f32 = 0.15;
const WIDEST_MAX: f32 = 0.75;
/// How far (a share of the leaf's length) a point may lie off the leaf's plane for it to be drawn as a card.
const FLAT: f32 = 0.08;
/// How much wider or narrower than the species' leaf the card may be made to keep its area.
const WIDTH_RANGE: (f32, f32) = (0.6, 2.0);

/// A leaf as a card: four corners in species space (petiole left and right, tip right and left, where right is
/// `+v`), its normal, and the alpha bytes of its corners.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Card {
    pub corners: [Vec3; 4],
    pub normal: Vec3,
    pub tags: [u8; 4],
}

impl Card {
    /// The two triangles, wound counter-clockwise seen from the side `normal` points to.
    pub(crate) const TRIANGLES: [u32; 6] = [0, 2, 1, 0, 3, 2];
}

/// The widest point, dequantised: level `k` of [`WIDEST_LEVELS`] over [`WIDEST_MIN`]..[`WIDEST_MAX`].
pub(crate) fn widest(k: u8) -> f32 {
    WIDEST_MIN + (WIDEST_MAX - WIDEST_MIN) * f32::from(k.min(WIDEST_LEVELS)) / f32::from(WIDEST_LEVELS)
}

/// The silhouette's half-width at `u` along the blade (0 petiole, 1 tip), as a share of the card's half-width,
/// for a blade widest at `w`: a sine lobe stretched so that it peaks at `w`, cut by eight teeth a margin that lean
/// toward the tip, 12 % deep. `segment.wgsl` `leaf_half_width` is the same function.
pub(crate) fn half_width(u: f32, w: f32) -> f32 {
    if u <= 0.0 || u >= 1.0 {
        return 0.0;
    }
    let t = if u < w { 0.5 * u / w } else { 0.5 + 0.5 * (u - w) / (1.0 - w) };
    let teeth = 1.0 - 0.12 * (u * 8.0).fract();
    (std::f32::consts::PI * t).sin() * teeth
}

/// The share of the card the silhouette covers, per widest level (the blade; the stalk is too thin to count).
fn fill(k: u8) -> f32 {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    let table = TABLE.get_or_init(|| {
        const STEPS: u32 = 2048;
        (0..=WIDEST_LEVELS)
            .map(|k| {
                let w = widest(k);
                (0..STEPS).map(|i| half_width((i as f32 + 0.5) / STEPS as f32, w)).sum::<f32>() / STEPS as f32
            })
            .collect()
    });
    table[usize::from(k.min(WIDEST_LEVELS))]
}

/// The alpha byte of a card corner.
fn tag(u: u8, right: bool, k: u8) -> u8 {
    u | u8::from(right) << 1 | k << 2
}

/// The leaf primitive `p` as a card, or `None` where it is not a leaf, not flat or has no area.
pub(crate) fn card_of(stream: &PrimitiveStream, p: &Primitive) -> Option<Card> {
    let Shape::Leaf { topology, .. } = p.shape else { return None };
    let points: Vec<Vec3> = stream.leaf(p).iter().map(|&l| Vec3::from(p.transform.point(l))).collect();
    if points.len() < 3 || !points.iter().all(|q| q.is_finite()) {
        return None;
    }
    // Twice the area, along the normal: the polygon's Newell sum, or the strip's triangles wound alike.
    let doubled = match topology {
        LeafTopology::Polygon => {
            (0..points.len()).map(|i| points[i].cross(points[(i + 1) % points.len()])).fold(Vec3::ZERO, |a, b| a + b)
        }
        LeafTopology::Strip => (0..points.len() - 2)
            .map(|k| {
                let (a, b, c) = if k % 2 == 0 { (k, k + 1, k + 2) } else { (k + 1, k, k + 2) };
                (points[b] - points[a]).cross(points[c] - points[a])
            })
            .fold(Vec3::ZERO, |a, b| a + b),
    };
    let area = doubled.length() / 2.0;
    let base = points[0];
    let tip = points.iter().copied().max_by(|a, b| a.distance_squared(base).total_cmp(&b.distance_squared(base)))?;
    let length = tip.distance(base);
    if !(area > 0.0 && length > 0.0 && area.is_finite()) {
        return None;
    }
    let normal = doubled.normalize();
    let axis = (tip - base) / length;
    if points.iter().any(|q| (*q - base).dot(normal).abs() > FLAT * length) {
        return None;
    }
    let side = normal.cross(axis).normalize();
    let (half, at) = points.iter().fold((0.0f32, 0.5f32), |(half, at), q| {
        let s = (*q - base).dot(side).abs();
        if s > half { (s, (*q - base).dot(axis) / length) } else { (half, at) }
    });
    if half <= 1e-4 * length {
        return None;
    }
    let k = ((at.clamp(WIDEST_MIN, WIDEST_MAX) - WIDEST_MIN) / (WIDEST_MAX - WIDEST_MIN) * f32::from(WIDEST_LEVELS))
        .round() as u8;
    let kept = (area / (fill(k) * length * 2.0)).clamp(half * WIDTH_RANGE.0, half * WIDTH_RANGE.1);
    let across = side * kept;
    Some(Card {
        corners: [base - across, base + across, tip + across, tip - across],
        normal,
        tags: [tag(0, false, k), tag(0, true, k), tag(1, true, k), tag(1, false, k)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_silhouette_peaks_where_the_leaf_is_widest_and_has_teeth() {
        for k in [0, 15, WIDEST_LEVELS] {
            let w = widest(k);
            let at = |u: f32| half_width(u, w);
            assert_eq!((at(0.0), at(1.0)), (0.0, 0.0));
            // The lobe's peak is at w (just below a tooth's notch it can be a little off).
            let peak = (1..1000).map(|i| i as f32 / 1000.0).max_by(|a, b| at(*a).total_cmp(&at(*b))).unwrap();
            assert!((peak - w).abs() < 0.13, "widest {w}, peak {peak}");
            // Teeth: the margin narrows within each eighth and jumps back at its end.
            assert!(at(0.5 - 1e-3) < at(0.5 + 1e-3));
            assert!((0.35..0.75).contains(&fill(k)), "{}", fill(k));
        }
    }

    #[test]
    fn tags_say_where_a_corner_is() {
        // Bit 7 tells a card's corner from any other vertex (whose alpha is 255).
        assert_eq!(tag(1, true, WIDEST_LEVELS), 0b0111_1111);
        assert_eq!(tag(0, false, 0), 0);
        assert_eq!(NOT_A_CARD & 0x80, 0x80);
    }
}
