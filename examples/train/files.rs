//! Reading and writing the commands' files: whole files, and float32 tensors of safetensors
//! files.

use safetensors::{Dtype, SafeTensors};
use std::path::{Path, PathBuf};

/// The directory `path` is in.
fn directory(path: &Path) -> &Path {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    }
}

/// The temporary file `write_atomically` writes `path` through: `.NAME.tmp` beside it, one name,
/// so that the next save of `path` replaces what a killed one left there.
fn temporary(path: &Path) -> Result<PathBuf, String> {
    let name = path
        .file_name()
        .ok_or_else(|| format!("cannot write {}: not a file name", path.display()))?;
    Ok(directory(path).join(format!(".{}.tmp", name.to_string_lossy())))
}

/// Removes the temporary file a save of `path` killed mid-write left behind, if any (a run's
/// start: its last save may never come again).
pub fn remove_leftover(path: &Path) {
    if let Ok(temporary) = temporary(path) {
        let _ = std::fs::remove_file(temporary);
    }
}

/// Writes `bytes` to `path` so that a crash or a full disk never leaves it half written: a
/// temporary file beside it, flushed to disk, renamed over it, the directory flushed. On failure
/// the old file is as it was and the temporary one is removed. (A kill mid-write leaves the
/// temporary file; the next save, or [`remove_leftover`], removes it.)
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let fail = |e: std::io::Error| format!("cannot write {}: {e}", path.display());
    let (dir, temporary) = (directory(path), temporary(path)?);
    let written = (|| {
        let mut file = std::fs::File::create(&temporary)?;
        std::io::Write::write_all(&mut file, bytes)?;
        file.sync_all()?;
        std::fs::rename(&temporary, path)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&temporary);
        return Err(fail(e));
    }
    // The rename is durable once the directory is; not every platform can open one to flush it.
    if let Ok(dir) = std::fs::File::open(dir) {
        let _ = dir.sync_all();
    }
    Ok(())
}

pub fn read(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// A float32 tensor of a safetensors file: shape and values.
pub fn f32_tensor(file: &SafeTensors<'_>, name: &str, path: &Path) -> Result<(Vec<usize>, Vec<f32>), String> {
    let view = file
        .tensor(name)
        .map_err(|_| format!("{}: no tensor `{name}`", path.display()))?;
    if view.dtype() != Dtype::F32 {
        return Err(format!(
            "{}: `{name}` is {:?}, expected F32",
            path.display(),
            view.dtype()
        ));
    }
    Ok((view.shape().to_vec(), bytemuck::pod_collect_to_vec(view.data())))
}

/// Writes named float32 tensors as a safetensors file.
pub fn write_f32(path: &Path, tensors: &[(String, Vec<usize>, Vec<f32>)]) -> Result<(), String> {
    let views = tensors
        .iter()
        .map(|(name, shape, values)| {
            safetensors::tensor::TensorView::new(Dtype::F32, shape.clone(), bytemuck::cast_slice(values))
                .map(|view| (name.clone(), view))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{e:?}"))?;
    safetensors::serialize_to_file(views, None, path).map_err(|e| format!("cannot write {}: {e:?}", path.display()))
}
