//! The drives a training command learns from and measures on: the episodes encoded, with their
//! mirror images (unless `--no-mirror`), split into training and held-out drives.

use crate::args::Data;
use crate::common::{encode_view, Encoded};
use drivesim::{Episodes, Model};
use std::path::Path;

/// Encoded training and held-out drives, and the training episodes' frame rate.
pub struct Drives {
    pub train: Vec<Encoded>,
    pub heldout: Vec<Encoded>,
    pub frame_hz: Option<f32>,
}

/// The drives of `episodes` encoded: as they are, then (unless `--no-mirror`) their mirror
/// images (`encode_view`), the mirrored drives in the same order after the plain ones.
fn views(model: &Model, episodes: &Episodes, data: &Data, threads: usize, what: &str) -> Result<Vec<Encoded>, String> {
    let mut drives = encode_view(model, episodes, threads, what, false)?;
    if !data.no_mirror {
        let mirrored = format!("{what}, mirrored");
        drives.extend(encode_view(model, episodes, threads, &mirrored, true)?);
    }
    Ok(drives)
}

/// The training and held-out drives: every view of the `--heldout` file's episodes, or of the
/// last `--holdout` episodes of `--episodes` (their mirror images held out with them).
pub fn split(model: &Model, data: &Data, threads: usize) -> Result<Drives, String> {
    let load = |path: &Path| Episodes::load(path).map_err(|e| format!("{}: {e}", path.display()));
    let all = load(&data.episodes)?;
    let frame_hz = all.frame_hz();
    let mut train = views(model, &all, data, threads, "episodes")?;
    if let Some(path) = &data.heldout {
        let heldout = views(model, &load(path)?, data, threads, "held-out episodes")?;
        return Ok(Drives {
            train,
            heldout,
            frame_hz,
        });
    }
    let (episodes, holdout) = (all.len(), data.holdout);
    if holdout >= episodes {
        return Err(format!("--holdout {holdout} leaves no training episode"));
    }
    let mut heldout = Vec::new();
    for view in (0..train.len() / episodes).rev() {
        let end = (view + 1) * episodes;
        heldout.extend(train.drain(end - holdout..end));
    }
    Ok(Drives {
        train,
        heldout,
        frame_hz,
    })
}
