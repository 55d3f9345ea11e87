//! Image comparison for the image tests (after wgpu's `tests/src/image.rs`): an image is checked against a
//! committed reference PNG within a tolerance; on failure `NAME-actual.png` and `NAME-difference.png` are written
//! next to the reference. A missing reference fails too, unless `CANOPY_BLESS=1` asks to write it.

#![allow(clippy::result_large_err)]

use std::path::{Path, PathBuf};

use super::offscreen::RenderedImage;

/// How different two images may be.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tolerance {
    /// A pixel differs when any channel differs by more than this.
    pub channel: u8,
    /// Fraction of pixels allowed to differ.
    pub max_fraction: f64,
    /// Largest mean absolute channel difference over the whole image (0..=255).
    pub max_mean: f64,
}

impl Default for Tolerance {
    fn default() -> Self {
        Tolerance { channel: 24, max_fraction: 0.01, max_mean: 1.5 }
    }
}

/// How two images compare.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Comparison {
    /// Pixels that differ beyond [`Tolerance::channel`].
    pub differing: usize,
    /// `differing` over all pixels.
    pub fraction: f64,
    /// Mean absolute channel difference (RGB).
    pub mean: f64,
    /// Largest channel difference.
    pub max: u8,
}

impl Comparison {
    /// Whether this is within `t`.
    pub fn within(&self, t: &Tolerance) -> bool {
        self.fraction <= t.max_fraction && self.mean <= t.max_mean
    }
}

/// Why an image check failed. (Its mismatch carries both reports and paths by value: it is the cold end of an image
/// test, where a large `Err` costs nothing.)
#[derive(Debug, thiserror::Error)]
pub enum CompareError {
    /// The images differ in size.
    #[error("size {0}×{1} differs from the reference's {2}×{3}")]
    Size(u32, u32, u32, u32),
    /// No reference image.
    #[error("no reference image {0} (run with CANOPY_BLESS=1 to write it; the render is in {1})")]
    Missing(PathBuf, PathBuf),
    /// The reference could not be read.
    #[error("reading {0}: {1}")]
    Read(PathBuf, String),
    /// The images differ beyond the tolerance.
    #[error("{path}: {c:?} exceeds {t:?}; see {actual} and {difference}", path = .reference.display(), actual = .actual.display(), difference = .difference.display())]
    Mismatch {
        /// The reference.
        reference: PathBuf,
        /// The measured difference.
        c: Comparison,
        /// The tolerance.
        t: Tolerance,
        /// Where the actual image went.
        actual: PathBuf,
        /// Where the difference image went.
        difference: PathBuf,
    },
    /// Writing an output image failed.
    #[error("writing {0}: {1}")]
    Write(PathBuf, String),
}

/// Compare two images of the same size (RGB; alpha is ignored).
pub fn compare(a: &RenderedImage, b: &RenderedImage, channel: u8) -> Result<Comparison, CompareError> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(CompareError::Size(a.width, a.height, b.width, b.height));
    }
    let (mut differing, mut sum, mut max) = (0usize, 0u64, 0u8);
    for (p, q) in a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)) {
        let d = (0..3).map(|i| p[i].abs_diff(q[i])).max().unwrap_or(0);
        sum += (0..3).map(|i| u64::from(p[i].abs_diff(q[i]))).sum::<u64>();
        max = max.max(d);
        if d > channel {
            differing += 1;
        }
    }
    let pixels = (a.width as usize * a.height as usize).max(1);
    Ok(Comparison {
        differing,
        fraction: differing as f64 / pixels as f64,
        mean: sum as f64 / (3 * pixels) as f64,
        max,
    })
}

/// The absolute difference, scaled ×4 for visibility, opaque.
pub fn difference_image(a: &RenderedImage, b: &RenderedImage) -> RenderedImage {
    let rgba = a
        .rgba
        .chunks_exact(4)
        .zip(b.rgba.chunks_exact(4))
        .flat_map(|(p, q)| {
            let d = |i: usize| p[i].abs_diff(q[i]).saturating_mul(4);
            [d(0), d(1), d(2), 255]
        })
        .collect();
    RenderedImage { width: a.width, height: a.height, rgba }
}

/// Load a PNG as RGBA8.
pub fn load_png(path: &Path) -> Result<RenderedImage, CompareError> {
    let img = image::open(path).map_err(|e| CompareError::Read(path.to_path_buf(), e.to_string()))?.to_rgba8();
    Ok(RenderedImage { width: img.width(), height: img.height(), rgba: img.into_raw() })
}

fn sibling(reference: &Path, suffix: &str) -> PathBuf {
    let stem = reference.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    reference.with_file_name(format!("{stem}-{suffix}.png"))
}

fn save(img: &RenderedImage, path: &Path) -> Result<(), CompareError> {
    img.save_png(path).map_err(|e| CompareError::Write(path.to_path_buf(), e.to_string()))
}

/// Check `actual` against the reference PNG at `reference` (see the module docs).
pub fn check_reference(actual: &RenderedImage, reference: &Path, t: &Tolerance) -> Result<Comparison, CompareError> {
    let actual_path = sibling(reference, "actual");
    let diff_path = sibling(reference, "difference");
    if !reference.exists() {
        if std::env::var_os("CANOPY_BLESS").is_some_and(|v| v == "1") {
            save(actual, reference)?;
            return Ok(Comparison { differing: 0, fraction: 0.0, mean: 0.0, max: 0 });
        }
        save(actual, &actual_path)?;
        return Err(CompareError::Missing(reference.to_path_buf(), actual_path));
    }
    let expected = load_png(reference)?;
    let c = compare(actual, &expected, t.channel)?;
    if c.within(t) {
        let _ = std::fs::remove_file(&actual_path);
        let _ = std::fs::remove_file(&diff_path);
        return Ok(c);
    }
    save(actual, &actual_path)?;
    save(&difference_image(actual, &expected), &diff_path)?;
    Err(CompareError::Mismatch {
        reference: reference.to_path_buf(),
        c,
        t: *t,
        actual: actual_path,
        difference: diff_path,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: u32, h: u32, f: impl Fn(u32, u32) -> [u8; 4]) -> RenderedImage {
        let f = &f;
        let rgba = (0..h).flat_map(|y| (0..w).flat_map(move |x| f(x, y))).collect();
        RenderedImage { width: w, height: h, rgba }
    }

    #[test]
    fn differences_are_counted_and_written() {
        let a = img(10, 10, |x, y| [(x * 20) as u8, (y * 20) as u8, 50, 255]);
        let mut b = a.clone();
        assert_eq!(compare(&a, &b, 0).unwrap().differing, 0);
        // Two pixels off by 100 in red, one by 5 in blue.
        b.rgba[0] = b.rgba[0].wrapping_add(100);
        b.rgba[4 * 55] = b.rgba[4 * 55].wrapping_add(100);
        b.rgba[4 * 70 + 2] += 5;
        let c = compare(&a, &b, 10).unwrap();
        assert_eq!((c.differing, c.max), (2, 100));
        assert!((c.fraction - 0.02).abs() < 1e-12);
        assert!((c.mean - 205.0 / 300.0).abs() < 1e-9);
        assert!(matches!(compare(&a, &img(5, 5, |_, _| [0; 4]), 0), Err(CompareError::Size(..))));

        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let reference = dir.join("scene.png");
        a.save_png(&reference).unwrap();
        let strict = Tolerance { channel: 10, max_fraction: 0.01, max_mean: 10.0 };
        let err = check_reference(&b, &reference, &strict).unwrap_err();
        assert!(matches!(err, CompareError::Mismatch { .. }), "{err}");
        assert!(dir.join("scene-actual.png").exists() && dir.join("scene-difference.png").exists());
        let diff = load_png(&dir.join("scene-difference.png")).unwrap();
        assert_eq!(diff.pixel(0, 0)[0], 255, "100 × 4 saturates");
        assert_eq!(diff.pixel(1, 0), [0, 0, 0, 255]);
        // Within a looser tolerance it passes and cleans up.
        let loose = Tolerance { channel: 10, max_fraction: 0.05, max_mean: 10.0 };
        assert!(check_reference(&b, &reference, &loose).is_ok());
        assert!(!dir.join("scene-actual.png").exists());
        // A missing reference fails (and leaves the render for inspection).
        let missing = dir.join("missing.png");
        if std::env::var_os("CANOPY_BLESS").is_none_or(|v| v != "1") {
            assert!(matches!(check_reference(&a, &missing, &loose), Err(CompareError::Missing(..))));
            assert!(dir.join("missing-actual.png").exists());
        }
    }
}
