//! Checkpoints of a training command, so that a run that stops (a kill, a power cut) resumes
//! where its last checkpoint was and writes the `--out` the run never stopped would have.
//!
//! A checkpoint file (`weights/TRAINING_FILES.md`, "Checkpoints"): the 8 bytes `DSCKPT01`, a
//! little-endian u32 `L`, `L` bytes of JSON (`command`, the `arguments` that decide the run,
//! `step`: steps done, `draw`: the data order's generator state as a decimal string), then the
//! trainer's state (`TransitionTrainer::save_state`, `VaeGanTrainer::save_state`). Written
//! atomically (`files.rs`).

use clap::Args;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"DSCKPT01";

// --checkpoint, --checkpoint-every, --resume: flattened into a command that checkpoints.
#[derive(Args, Clone)]
pub struct Checkpointing {
    /// Checkpoint file: written every --checkpoint-every steps, read by --resume
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Steps between checkpoints
    #[arg(long, default_value_t = 500, value_parser = clap::value_parser!(u32).range(1..))]
    pub checkpoint_every: u32,
    /// Go on from --checkpoint where it exists (a run of the same arguments); start afresh
    /// where it does not
    #[arg(long, requires = "checkpoint")]
    pub resume: bool,
}

impl Checkpointing {
    /// Whether a checkpoint is due after `done` of `steps` steps (not after the last: `--out` is).
    pub fn due(&self, done: usize, steps: usize) -> bool {
        self.checkpoint.is_some() && done < steps && done.is_multiple_of(self.checkpoint_every as usize)
    }

    /// Room for a trainer's state of `len` bytes, where there are checkpoints to write.
    pub fn buffer(&self, len: usize) -> Vec<u8> {
        vec![0; if self.checkpoint.is_some() { len } else { 0 }]
    }

    /// Where `command`'s run goes on from: with `--resume` and a checkpoint there (it must be
    /// `command`'s, with the same `arguments`), `load` gets the trainer's state and this returns
    /// the steps done and the data order's generator state; `None` starts afresh.
    pub fn restore(
        &self,
        command: &str,
        arguments: &str,
        load: impl FnOnce(&[u8]) -> Result<(), drivesim::Error>,
    ) -> Result<Option<(usize, u64)>, String> {
        if let Some(path) = &self.checkpoint {
            crate::files::remove_leftover(path);
        }
        let Some(path) = self.checkpoint.as_ref().filter(|p| self.resume && p.exists()) else {
            return Ok(None);
        };
        let bad = |why: String| format!("{}: not a checkpoint to resume from: {why}", path.display());
        let bytes = crate::files::read(path)?;
        if bytes.len() < 12 || &bytes[..8] != MAGIC {
            return Err(bad("it does not begin with DSCKPT01".into()));
        }
        let len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
        let header = bytes.get(12..12 + len).ok_or_else(|| bad("truncated".into()))?;
        let header: serde_json::Value = serde_json::from_slice(header).map_err(|e| bad(e.to_string()))?;
        let field = |name: &str| header.get(name).ok_or_else(|| bad(format!("no `{name}`")));
        if field("command")?.as_str() != Some(command) {
            return Err(bad(format!(
                "it is a checkpoint of `{}`, not of `{command}`",
                field("command")?
            )));
        }
        let theirs = field("arguments")?.as_str().unwrap_or_default();
        if theirs != arguments {
            return Err(bad(format!(
                "its run had other arguments:\n  {theirs}\nnot\n  {arguments}"
            )));
        }
        let step = field("step")?
            .as_u64()
            .ok_or_else(|| bad("`step` is not a count".into()))? as usize;
        let draw = field("draw")?.as_str().and_then(|s| s.parse().ok());
        let draw = draw.ok_or_else(|| bad("`draw` is not a decimal u64".into()))?;
        load(&bytes[12 + len..]).map_err(|e| bad(e.to_string()))?;
        println!("resumed at step {step}");
        Ok(Some((step, draw)))
    }

    /// Writes the checkpoint after `step` steps.
    pub fn save(&self, command: &str, arguments: &str, step: usize, draw: u64, state: &[u8]) -> Result<(), String> {
        let path: &Path = self.checkpoint.as_deref().expect("due() checked --checkpoint");
        let header = serde_json::json!({
            "command": command,
            "arguments": arguments,
            "step": step,
            "draw": draw.to_string(),
        })
        .to_string();
        let mut bytes = Vec::with_capacity(12 + header.len() + state.len());
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&(header.len() as u32).to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend_from_slice(state);
        crate::files::write_atomically(path, &bytes)
    }
}
