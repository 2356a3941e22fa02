//! Checkpoint loading / saving (network.md §12).
//!
//! Official checkpoints (`.pth` zip pickle from DDP with a `module.` prefix, or `.safetensors`
//! with the bare state-dict names) are loaded strictly through `burn-store`: the key table
//! below renames official keys onto this crate's module paths, `PyTorchToBurnAdapter`
//! transposes `nn::Linear` weights and maps norm `weight`/`bias` to `gamma`/`beta`, sparse-conv
//! kernels stay raw (`[C_out, 3, 3, 3, C_in]`). Every model parameter must be found, every file
//! tensor used (except `num_batches_tracked`), every shape right; otherwise
//! [`ModelError::CheckpointMismatch`] lists the offenders.
//!
//! ## Key table (official -> Burn path), applied top to bottom, each rule to the result of the previous
//!
//! | # | official pattern (regex) | Burn path | module |
//! |---|---|---|---|
//! | 1 | `^module\.` | (removed) | DDP prefix |
//! | 2 | `^backbone\.backbone\.embedding\.0\.` | `embedding.linear.` | stem Linear |
//! | 3 | `^backbone\.backbone\.embedding\.1\.` | `embedding.norm.` | stem BatchNorm |
//! | 4 | `^backbone\.backbone\.enc\.enc(\d+)\.down\.proj\.` | `enc.$1.down.proj.` | pooling Linear |
//! | 5 | `^backbone\.backbone\.enc\.enc(\d+)\.down\.norm\.0\.` | `enc.$1.down.norm.` | pooling BatchNorm |
//! | 6 | `^backbone\.backbone\.enc\.enc(\d+)\.block(\d+)\.` | `enc.$1.blocks.$2.` | encoder block |
//! | 7 | `^backbone\.backbone\.dec\.dec(\d+)\.up\.proj\.0\.` | `dec.$1.up.proj.linear.` | unpool coarse Linear |
//! | 8 | `^backbone\.backbone\.dec\.dec(\d+)\.up\.proj\.1\.` | `dec.$1.up.proj.norm.` | unpool coarse BatchNorm |
//! | 9 | `^backbone\.backbone\.dec\.dec(\d+)\.up\.proj_skip\.0\.` | `dec.$1.up.proj_skip.linear.` | unpool skip Linear |
//! | 10 | `^backbone\.backbone\.dec\.dec(\d+)\.up\.proj_skip\.1\.` | `dec.$1.up.proj_skip.norm.` | unpool skip BatchNorm |
//! | 11 | `^backbone\.backbone\.dec\.dec(\d+)\.block(\d+)\.` | `dec.$1.blocks.$2.` | decoder block |
//! | 12 | `\.cpe\.0\.` | `.cpe.conv.` | SubMConv3d (raw KRSC kernel) |
//! | 13 | `\.cpe\.1\.` | `.cpe.linear.` | xCPE Linear |
//! | 14 | `\.cpe\.2\.` | `.cpe.norm.` | xCPE LayerNorm |
//! | 15 | `\.norm1\.0\.` | `.norm1.` | LN1 |
//! | 16 | `\.norm2\.0\.` | `.norm2.` | LN2 |
//! | 17 | `\.mlp\.0\.fc1\.` | `.mlp.fc1.` | MLP Linear 1 |
//! | 18 | `\.mlp\.0\.fc2\.` | `.mlp.fc2.` | MLP Linear 2 |
//! | 19 | `^head\.0\.` | `head.fc1.` | head Linear 1 |
//! | 20 | `^head\.2\.` | `head.fc2.` | head Linear 2 |
//! | 21 | `^head\.4\.` | `head.fc3.` | head Linear 3 |
//!
//! Unchanged: `ff_type_embed`, `dlt_type_embed`, `attn.qkv.*`, `attn.proj.*`. Norm leaves
//! `weight`/`bias` become `gamma`/`beta` in the adapter; `running_mean`/`running_var` keep
//! their names; `num_batches_tracked` (0-d i64) is ignored.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn_store::{
    ApplyResult, KeyRemapper, ModuleSnapshot, PyTorchToBurnAdapter, PytorchStore, SafetensorsStore,
};

use crate::error::{ModelError, Result};
use crate::model::Ggpt;

/// The official -> Burn key table (see the module docs), `(regex, replacement)`.
pub const KEY_TABLE: [(&str, &str); 21] = [
    (r"^module\.", ""),
    (r"^backbone\.backbone\.embedding\.0\.", "embedding.linear."),
    (r"^backbone\.backbone\.embedding\.1\.", "embedding.norm."),
    (
        r"^backbone\.backbone\.enc\.enc(\d+)\.down\.proj\.",
        "enc.${1}.down.proj.",
    ),
    (
        r"^backbone\.backbone\.enc\.enc(\d+)\.down\.norm\.0\.",
        "enc.${1}.down.norm.",
    ),
    (
        r"^backbone\.backbone\.enc\.enc(\d+)\.block(\d+)\.",
        "enc.${1}.blocks.${2}.",
    ),
    (
        r"^backbone\.backbone\.dec\.dec(\d+)\.up\.proj\.0\.",
        "dec.${1}.up.proj.linear.",
    ),
    (
        r"^backbone\.backbone\.dec\.dec(\d+)\.up\.proj\.1\.",
        "dec.${1}.up.proj.norm.",
    ),
    (
        r"^backbone\.backbone\.dec\.dec(\d+)\.up\.proj_skip\.0\.",
        "dec.${1}.up.proj_skip.linear.",
    ),
    (
        r"^backbone\.backbone\.dec\.dec(\d+)\.up\.proj_skip\.1\.",
        "dec.${1}.up.proj_skip.norm.",
    ),
    (
        r"^backbone\.backbone\.dec\.dec(\d+)\.block(\d+)\.",
        "dec.${1}.blocks.${2}.",
    ),
    (r"\.cpe\.0\.", ".cpe.conv."),
    (r"\.cpe\.1\.", ".cpe.linear."),
    (r"\.cpe\.2\.", ".cpe.norm."),
    (r"\.norm1\.0\.", ".norm1."),
    (r"\.norm2\.0\.", ".norm2."),
    (r"\.mlp\.0\.fc1\.", ".mlp.fc1."),
    (r"\.mlp\.0\.fc2\.", ".mlp.fc2."),
    (r"^head\.0\.", "head.fc1."),
    (r"^head\.2\.", "head.fc2."),
    (r"^head\.4\.", "head.fc3."),
];

/// Name suffix of the BatchNorm step counters, present in official files and ignored.
pub const IGNORED_SUFFIX: &str = "num_batches_tracked";

fn remapper(path: &Path) -> Result<KeyRemapper> {
    KeyRemapper::from_patterns(KEY_TABLE.to_vec()).map_err(|e| ModelError::CheckpointRead {
        path: path.to_path_buf(),
        message: format!("invalid key table: {e}"),
    })
}

/// Official key of a Burn module path (inverse of [`KEY_TABLE`], for error messages).
pub fn official_key(burn_path: &str) -> String {
    let mut parts: Vec<String> = burn_path.split('.').map(str::to_string).collect();
    // leaf renames of the adapter
    if let Some(last) = parts.last_mut() {
        if last == "gamma" {
            *last = "weight".into();
        } else if last == "beta" {
            *last = "bias".into();
        }
    }
    let joined = parts.join(".");
    let mut s = joined.clone();
    let rules: [(&str, &str); 10] = [
        (".cpe.conv.", ".cpe.0."),
        (".cpe.linear.", ".cpe.1."),
        (".cpe.norm.", ".cpe.2."),
        (".norm1.", ".norm1.0."),
        (".norm2.", ".norm2.0."),
        (".mlp.fc1.", ".mlp.0.fc1."),
        (".mlp.fc2.", ".mlp.0.fc2."),
        (".up.proj.linear.", ".up.proj.0."),
        (".up.proj.norm.", ".up.proj.1."),
        (".down.norm.", ".down.norm.0."),
    ];
    for (from, to) in rules {
        s = s.replace(from, to);
    }
    s = s
        .replace(".up.proj_skip.linear.", ".up.proj_skip.0.")
        .replace(".up.proj_skip.norm.", ".up.proj_skip.1.");
    let mut segs: Vec<String> = s.split('.').map(str::to_string).collect();
    if segs.len() >= 2 && (segs[0] == "enc" || segs[0] == "dec") {
        let kind = segs[0].clone();
        let stage = segs[1].clone();
        let mut out = vec![
            "backbone".to_string(),
            "backbone".to_string(),
            kind.clone(),
            format!("{kind}{stage}"),
        ];
        let mut rest = segs.split_off(2);
        if rest.len() >= 2 && rest[0] == "blocks" {
            let i = rest[1].clone();
            rest.drain(0..2);
            out.push(format!("block{i}"));
        }
        out.extend(rest);
        return out.join(".");
    }
    if s.starts_with("embedding.linear.") {
        return s.replacen("embedding.linear.", "backbone.backbone.embedding.0.", 1);
    }
    if s.starts_with("embedding.norm.") {
        return s.replacen("embedding.norm.", "backbone.backbone.embedding.1.", 1);
    }
    for (from, to) in [
        ("head.fc1.", "head.0."),
        ("head.fc2.", "head.2."),
        ("head.fc3.", "head.4."),
    ] {
        if s.starts_with(from) {
            return s.replacen(from, to, 1);
        }
    }
    s
}

/// Turns an `ApplyResult` into `Ok` or a strict-loading error naming every offending key.
fn check_strict(path: &Path, result: &ApplyResult) -> Result<()> {
    let missing: Vec<String> = result
        .missing
        .iter()
        .map(|(p, _)| format!("{p} (official key {})", official_key(p)))
        .collect();
    let unused: Vec<String> = result
        .unused
        .iter()
        .filter(|k| !k.ends_with(IGNORED_SUFFIX))
        .cloned()
        .collect();
    let invalid: Vec<String> = result.errors.iter().map(|e| e.to_string()).collect();
    if missing.is_empty() && unused.is_empty() && invalid.is_empty() {
        return Ok(());
    }
    let mut details = String::new();
    for (title, list) in [
        ("missing", &missing),
        ("unused", &unused),
        ("invalid", &invalid),
    ] {
        for item in list.iter() {
            details.push_str(&format!("  {title}: {item}\n"));
        }
    }
    Err(ModelError::CheckpointMismatch {
        path: path.to_path_buf(),
        missing,
        unused,
        invalid,
        details,
    })
}

/// Checkpoint formats this crate reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CheckpointFormat {
    /// torch zip pickle (`.pth`, `.pt`), official keys, optional `module.` prefix.
    Pytorch,
    /// safetensors with official keys (optional `module.` prefix).
    Safetensors,
    /// This crate's own burnpack (`.bpk`), Burn paths.
    Burnpack,
}

impl CheckpointFormat {
    /// Format from the file extension.
    pub fn from_path(path: &Path) -> Result<Self> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("pth" | "pt" | "bin" | "ckpt") => Ok(Self::Pytorch),
            Some("safetensors") => Ok(Self::Safetensors),
            Some("bpk" | "burnpack") => Ok(Self::Burnpack),
            other => Err(ModelError::CheckpointRead {
                path: path.to_path_buf(),
                message: format!(
                    "unknown checkpoint extension {other:?} (expected .pth, .safetensors or .bpk)"
                ),
            }),
        }
    }
}

/// Loads an official checkpoint (`.pth` / `.safetensors`) or a burnpack into `model`, strictly.
pub fn load_checkpoint(model: Ggpt, path: &Path) -> Result<Ggpt> {
    match CheckpointFormat::from_path(path)? {
        CheckpointFormat::Pytorch => load_pytorch(model, path),
        CheckpointFormat::Safetensors => load_safetensors(model, path),
        CheckpointFormat::Burnpack => load_burnpack(model, path),
    }
}

/// Loads an official `.pth` (torch zip pickle) strictly.
pub fn load_pytorch(mut model: Ggpt, path: &Path) -> Result<Ggpt> {
    if !path.is_file() {
        return Err(ModelError::CheckpointRead {
            path: path.to_path_buf(),
            message: "no such file".into(),
        });
    }
    let mut store = PytorchStore::from_file(path)
        .remap(remapper(path)?)
        .map_indices_contiguous(false)
        .allow_partial(true)
        .validate(false);
    let result = model
        .load_from(&mut store)
        .map_err(|e| ModelError::CheckpointRead {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    check_strict(path, &result)?;
    Ok(model)
}

/// Loads an official `.safetensors` strictly.
pub fn load_safetensors(model: Ggpt, path: &Path) -> Result<Ggpt> {
    if !path.is_file() {
        return Err(ModelError::CheckpointRead {
            path: path.to_path_buf(),
            message: "no such file".into(),
        });
    }
    let bytes = std::fs::read(path).map_err(|e| ModelError::CheckpointRead {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    load_safetensors_bytes(model, bytes, path)
}

/// Loads official `.safetensors` bytes strictly (the embedded shipped model); `name` is the
/// path reported in errors.
pub fn load_safetensors_bytes(mut model: Ggpt, bytes: Vec<u8>, name: &Path) -> Result<Ggpt> {
    let mut store = SafetensorsStore::from_bytes(Some(bytes))
        .with_from_adapter(PyTorchToBurnAdapter)
        .remap(remapper(name)?)
        .map_indices_contiguous(false)
        .allow_partial(true)
        .validate(false);
    let result = model
        .load_from(&mut store)
        .map_err(|e| ModelError::CheckpointRead {
            path: name.to_path_buf(),
            message: e.to_string(),
        })?;
    check_strict(name, &result)?;
    Ok(model)
}

/// Loads one of this crate's burnpack checkpoints strictly.
pub fn load_burnpack(mut model: Ggpt, path: &Path) -> Result<Ggpt> {
    if !path.is_file() {
        return Err(ModelError::CheckpointRead {
            path: path.to_path_buf(),
            message: "no such file".into(),
        });
    }
    // Read the whole file now: a file-backed store materialises tensors lazily, which would
    // break if the file is replaced or deleted after loading.
    let bytes = std::fs::read(path).map_err(|e| ModelError::CheckpointRead {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut store =
        burn_store::BurnpackStore::from_bytes(Some(burn::tensor::Bytes::from_bytes_vec(bytes)))
            .allow_partial(true)
            .validate(false);
    let result = model
        .load_from(&mut store)
        .map_err(|e| ModelError::CheckpointRead {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    check_strict(path, &result)?;
    Ok(model)
}

/// Saves `model` as burnpack at `path`, atomically (temporary file in the same folder, then rename).
pub fn save_burnpack(model: &Ggpt, path: &Path) -> Result<()> {
    let err = |message: String| ModelError::CheckpointWrite {
        path: path.to_path_buf(),
        message,
    };
    let file_name = path
        .file_name()
        .and_then(|f| f.to_str())
        .ok_or_else(|| err("no file name".into()))?;
    let tmp: PathBuf = path.with_file_name(format!(".{file_name}.tmp{}", std::process::id()));
    let mut store = burn_store::BurnpackStore::from_file(&tmp)
        .overwrite(true)
        .auto_extension(false);
    model
        .save_into(&mut store)
        .map_err(|e| err(e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        err(format!("rename: {e}"))
    })
}

/// Number of trainable parameters of `model` (network.md §1.3: buffers excluded). Burn's
/// `num_params` also counts the BatchNorm running statistics, which are skipped here.
pub fn num_trainable_params(model: &Ggpt) -> usize {
    struct Counter {
        path: Vec<String>,
        count: usize,
    }
    impl burn::module::ModuleVisitor for Counter {
        fn enter_module(&mut self, name: &str, _container_type: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container_type: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(
            &mut self,
            param: &burn::module::Param<burn::tensor::Tensor<D>>,
        ) {
            let leaf = self.path.last().map(String::as_str);
            if !matches!(leaf, Some("running_mean" | "running_var")) {
                self.count += param.lazy_shape().num_elements();
            }
        }
    }
    let mut c = Counter {
        path: Vec::new(),
        count: 0,
    };
    model.visit(&mut c);
    c.count
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn official_key_inverts_the_table() {
        let cases = [
            (
                "enc.1.blocks.0.cpe.conv.weight",
                "backbone.backbone.enc.enc1.block0.cpe.0.weight",
            ),
            (
                "enc.1.blocks.0.cpe.norm.gamma",
                "backbone.backbone.enc.enc1.block0.cpe.2.weight",
            ),
            (
                "dec.3.up.proj_skip.norm.running_var",
                "backbone.backbone.dec.dec3.up.proj_skip.1.running_var",
            ),
            (
                "dec.0.up.proj.linear.weight",
                "backbone.backbone.dec.dec0.up.proj.0.weight",
            ),
            (
                "enc.2.down.norm.beta",
                "backbone.backbone.enc.enc2.down.norm.0.bias",
            ),
            (
                "embedding.norm.running_mean",
                "backbone.backbone.embedding.1.running_mean",
            ),
            ("head.fc3.bias", "head.4.bias"),
            (
                "dec.0.blocks.1.mlp.fc2.weight",
                "backbone.backbone.dec.dec0.block1.mlp.0.fc2.weight",
            ),
            ("ff_type_embed", "ff_type_embed"),
        ];
        let remap = KeyRemapper::from_patterns(KEY_TABLE.to_vec()).expect("valid regexes");
        for (burn, official) in cases {
            assert_eq!(official_key(burn), official);
            // forward direction through the same regex table (modulo gamma/beta, done by the adapter)
            let mut s = format!("module.{official}");
            for (re, rep) in remap.to_regex_pairs() {
                s = re.replace_all(&s, rep.as_str()).to_string();
            }
            let burn_norm = burn.replace(".gamma", ".weight").replace(".beta", ".bias");
            assert_eq!(s, burn_norm, "{official}");
        }
    }
}
