//! Reading and writing the commands' files: whole files, and float32 tensors of safetensors
//! files.

use safetensors::{Dtype, SafeTensors};
use std::path::Path;

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
