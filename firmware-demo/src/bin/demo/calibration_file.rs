//! The camera calibration file: TOML with the intrinsics of the model-input image and the
//! camera <- robot-base transform, both row-major.
//!
//! ```toml
//! # K of the image the model sees (pixels; pixel centres at integers, OpenCV convention).
//! intrinsics = [[115.2, 0.0, 63.5], [0.0, 115.2, 63.5], [0.0, 0.0, 1.0]]
//! # T: X_cam = R X_base + t (metres).
//! extrinsics = [
//!     [0.0, 1.0, 0.0, 0.0],
//!     [0.447, 0.0, -0.894, -0.089],
//!     [-0.894, 0.0, -0.447, 1.52],
//!     [0.0, 0.0, 0.0, 1.0],
//! ]
//! ```

use std::path::Path;

use anyhow::Context as _;
use firmware_demo::Calibration;
use serde::{Deserialize, Serialize};

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct CalibrationToml {
    intrinsics: [[f32; 3]; 3],
    extrinsics: [[f32; 4]; 4],
}

/// Parses and checks a calibration (the engine rejects a K that is not a pinhole matrix and a
/// T that is not a rigid transform).
pub fn parse(text: &str) -> anyhow::Result<Calibration> {
    let file: CalibrationToml = toml::from_str(text)?;
    let calibration = Calibration {
        intrinsics: file.intrinsics,
        extrinsics: file.extrinsics,
    };
    calibration.camera()?;
    Ok(calibration)
}

pub fn load(path: &Path) -> anyhow::Result<Calibration> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the camera calibration", path.display()))?;
    parse(&text).with_context(|| format!("{}: bad camera calibration", path.display()))
}

/// The calibration as a file [`parse`] reads back.
pub fn to_toml(calibration: &Calibration) -> String {
    let file = CalibrationToml {
        intrinsics: calibration.intrinsics,
        extrinsics: calibration.extrinsics,
    };
    toml::to_string(&file).expect("arrays of floats always serialize")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_file_is_the_default_metaworld_camera() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("calibration/metaworld.toml");
        let shipped = load(&path).unwrap();
        let default = Calibration::default_for(128, 128);
        assert_eq!(shipped.intrinsics, default.intrinsics);
        let close = shipped
            .extrinsics
            .iter()
            .flatten()
            .zip(default.extrinsics.iter().flatten())
            .all(|(a, b)| (a - b).abs() < 1e-6);
        assert!(close, "{shipped:?}\n{default:?}");
    }

    #[test]
    fn round_trips_through_toml() {
        let default = Calibration::default_for(320, 240);
        assert_eq!(parse(&to_toml(&default)).unwrap(), default);
    }

    #[test]
    fn rejects_what_is_not_a_camera() {
        let scaled = "intrinsics = [[100.0, 0.0, 10.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]]\n\
                      extrinsics = [[2.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], \
                      [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0]]";
        let error = parse(scaled).unwrap_err().to_string();
        assert!(error.contains("rigid"), "{error}");
        let negative_focal = scaled
            .replace("[[100.0", "[[-100.0")
            .replace("2.0, 0.0, 0.0, 0.0", "1.0, 0.0, 0.0, 0.0");
        assert!(parse(&negative_focal).is_err());
        let typo = "intrinsic = [[100.0, 0.0, 10.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]]";
        assert!(
            parse(typo)
                .unwrap_err()
                .to_string()
                .contains("unknown field")
        );
    }
}
