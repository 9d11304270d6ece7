//! A trainer's state as bytes (checkpoints), into and from the caller's bytes, so that saving
//! needs no allocator: 8 bytes naming the trainer and the format, little-endian u32 words (the
//! sizes the state is for, then the Adam steps taken), then the saved buffers' values as
//! little-endian f32, back to back. `weights/TRAINING_FILES.md` ("Checkpoints") gives each
//! trainer's.

use crate::error::expect_len;
use crate::{Error, Result};
use alloc::format;

/// Bytes of a state of `words` header words and `floats` values.
pub(super) fn state_len(words: usize, floats: usize) -> usize {
    8 + 4 * (words + floats)
}

/// Writes `magic`, `words` and `buffers` into `out` (exactly [`state_len`] bytes).
pub(super) fn write_state(out: &mut [u8], magic: &[u8; 8], words: &[u32], buffers: &[&[f32]]) -> Result<()> {
    let floats = buffers.iter().map(|b| b.len()).sum();
    expect_len("out", out, state_len(words.len(), floats))?;
    let (head, values) = out.split_at_mut(8 + 4 * words.len());
    head[..8].copy_from_slice(magic);
    for (slot, w) in head[8..].chunks_exact_mut(4).zip(words) {
        slot.copy_from_slice(&w.to_le_bytes());
    }
    let all = buffers.iter().flat_map(|b| b.iter());
    for (slot, v) in values.chunks_exact_mut(4).zip(all) {
        slot.copy_from_slice(&v.to_le_bytes());
    }
    Ok(())
}

/// Reads a state [`write_state`] wrote: its sizes must be `sizes` (the words before the last),
/// every value finite; only then are `buffers` filled. Returns the last word (the steps taken).
/// Anything else is [`Error::Malformed`] (`what`: the trainer's name) or [`Error::BadWeight`],
/// and leaves `buffers` unchanged.
pub(super) fn read_state(
    state: &[u8],
    magic: &[u8; 8],
    what: &'static str,
    sizes: &[u32],
    buffers: &mut [&mut [f32]],
) -> Result<u32> {
    let floats: usize = buffers.iter().map(|b| b.len()).sum();
    let expected = state_len(sizes.len() + 1, floats);
    if state.len() != expected || !state.starts_with(magic) {
        return Err(Error::Malformed {
            what,
            reason: format!(
                "expected {expected} bytes beginning with {magic:?}, found {}",
                state.len()
            ),
        });
    }
    let word = |i: usize| u32::from_le_bytes(state[8 + 4 * i..][..4].try_into().expect("4 bytes"));
    let found: alloc::vec::Vec<u32> = (0..sizes.len()).map(word).collect();
    if found != sizes {
        return Err(Error::Malformed {
            what,
            reason: format!("a state for sizes {found:?}, this trainer's are {sizes:?}"),
        });
    }
    let values = state[8 + 4 * (sizes.len() + 1)..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")));
    if let Some((index, value)) = values.clone().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(Error::BadWeight {
            name: what.into(),
            index,
            value,
            expected: "a finite number",
        });
    }
    let mut values = values;
    for buffer in buffers.iter_mut() {
        buffer.iter_mut().zip(&mut values).for_each(|(slot, v)| *slot = v);
    }
    Ok(word(sizes.len()))
}
