//! Checkpoints `checkpoints/step-XXXXXXXX/{model.bpk, optim.bpk, state.json}`: written into a
//! temporary directory and renamed (atomic), listed, loaded (the optimizer state checked before
//! Burn sees it), and the temporaries of dead processes removed.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::ModuleOptimizer;
use burn::tensor::{Device, Tensor};
use ggpt_model::Ggpt;

use super::{TrainState, adam};
use crate::error::{Result, TrainError, io_err};

/// Directory of the checkpoint of `step`.
pub fn checkpoint_dir(out: &Path, step: u64) -> PathBuf {
    out.join("checkpoints").join(format!("step-{step:08}"))
}

/// Writes a checkpoint atomically (temporary directory + rename) and prunes old ones.
pub fn save_checkpoint(
    out: &Path,
    model: &Ggpt,
    optim: &ModuleOptimizer,
    state: &TrainState,
) -> Result<PathBuf> {
    let root = out.join("checkpoints");
    std::fs::create_dir_all(&root).map_err(io_err(&root))?;
    let final_dir = checkpoint_dir(out, state.step);
    let tmp = root.join(format!(
        "{CHECKPOINT_TMP_PREFIX}{:08}-{}",
        state.step,
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(io_err(&tmp))?;
    }
    std::fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
    let ck = |message: String| TrainError::Checkpoint {
        path: tmp.clone(),
        message,
    };
    ggpt_model::weights::save_burnpack(&model.valid(), &tmp.join("model.bpk"))?;
    optim
        .save(tmp.join("optim.bpk"))
        .map_err(|e| ck(format!("optimizer: {e:?}")))?;
    let text = serde_json::to_string_pretty(state).map_err(|e| ck(e.to_string()))?;
    std::fs::write(tmp.join("state.json"), text).map_err(io_err(tmp.join("state.json")))?;
    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(io_err(&final_dir))?;
    }
    std::fs::rename(&tmp, &final_dir).map_err(io_err(&final_dir))?;
    // prune
    let mut all = list_checkpoints(out)?;
    let keep = state.options.keep_checkpoints.max(1);
    while all.len() > keep {
        let (_, old) = all.remove(0);
        let _ = std::fs::remove_dir_all(old);
    }
    Ok(final_dir)
}

/// Complete checkpoints of a run, oldest first.
pub fn list_checkpoints(out: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let root = out.join("checkpoints");
    let mut v = Vec::new();
    if !root.is_dir() {
        return Ok(v);
    }
    for e in std::fs::read_dir(&root).map_err(io_err(&root))? {
        let e = e.map_err(io_err(&root))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if let Some(n) = name
            .strip_prefix("step-")
            .and_then(|s| s.parse::<u64>().ok())
            && e.path().join("state.json").is_file()
        {
            v.push((n, e.path()));
        }
    }
    v.sort();
    Ok(v)
}

/// Loads a checkpoint directory: model (on `device`, training mode), optimizer, state.
pub fn load_checkpoint(dir: &Path, device: &Device) -> Result<(Ggpt, ModuleOptimizer, TrainState)> {
    let state_path = dir.join("state.json");
    let text = std::fs::read_to_string(&state_path).map_err(io_err(&state_path))?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| TrainError::Format {
        path: state_path.clone(),
        message: e.to_string(),
    })?;
    state
        .options
        .model
        .validate()
        .map_err(|m| TrainError::Format {
            path: state_path.clone(),
            message: format!("options.model: {m}"),
        })?;
    let plain = device.clone().without_autodiff();
    let model = Ggpt::new(&state.options.model, &plain);
    let weights = dir.join("model.bpk");
    // The architecture comes from state.json: a mismatch is in either file, so both are named.
    let model = ggpt_model::weights::load_burnpack(model, &weights).map_err(|e| {
        TrainError::Checkpoint {
            path: weights.clone(),
            message: format!(
                "{e} (the network architecture is the one recorded in {})",
                state_path.display()
            ),
        }
    })?;
    let optim = load_optimizer(&dir.join("optim.bpk"), &model, &weights, state.step)?;
    Ok((model.fork(device).train(), optim, state))
}

/// Key suffix of the per-parameter rank scalar in Burn 0.22.1's optimizer records
/// (`burn-optim` `module_optimizer.rs`, `RANK_KEY`).
const OPTIM_RANK_SUFFIX: &str = ".__rank";

/// Reads the Adam state `optim.bpk` of a checkpoint of `model` after `step` steps, checking it
/// before Burn sees it: Burn 0.22.1's `ModuleOptimizer::load_record` panics on a state tensor
/// without a parameter id, and silently drops the state of a parameter it cannot rebuild (a
/// corrupt file would crash, or quietly restart Adam's moments and break exact resume). Here
/// every state tensor must carry the id its name starts with, every recorded parameter must be
/// one of the model's (some, after the first step), and every tensor must survive the load.
/// `model_origin` is the file `model` was loaded from (named in a mismatch).
pub fn load_optimizer(
    path: &Path,
    model: &Ggpt,
    model_origin: &Path,
    step: u64,
) -> Result<ModuleOptimizer> {
    let err = |message: String| TrainError::Checkpoint {
        path: path.to_path_buf(),
        message,
    };
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let reader = burn_pack::Reader::from_bytes(burn_pack::Bytes::from_bytes_vec(bytes.clone()))
        .map_err(|e| err(format!("not an optimizer record: {e}")))?;
    let ranked: BTreeSet<u64> = reader
        .scalars()
        .keys()
        .filter_map(|k| k.strip_suffix(OPTIM_RANK_SUFFIX)?.parse().ok())
        .collect();
    let tensors = reader
        .into_tensors()
        .map_err(|e| err(format!("corrupt optimizer record: {e}")))?;
    for t in &tensors {
        let id = t
            .param_id
            .ok_or_else(|| err(format!("state tensor {} carries no parameter id", t.name)))?;
        if !t.name.starts_with(&format!("{id}.")) || !ranked.contains(&id) {
            return Err(err(format!(
                "state tensor {} does not belong to a recorded parameter (id {id})",
                t.name
            )));
        }
    }
    struct Ids(BTreeSet<u64>);
    impl ModuleVisitor for Ids {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.insert(param.id.val());
        }
    }
    let mut ids = Ids(BTreeSet::new());
    model.visit(&mut ids);
    // Parameters that never received a gradient have no state; a state of a parameter the
    // network does not have would be ignored by Burn, and after a step there is some state.
    let foreign = ranked.difference(&ids.0).count();
    if foreign > 0 || (step > 0 && ranked.is_empty()) {
        return Err(err(format!(
            "state of {} parameters, {foreign} of them not parameters of the network loaded from {} (step {step}; the parameter ids of the two files must match)",
            ranked.len(),
            model_origin.display()
        )));
    }
    let optim = adam()
        .from_bytes(burn_pack::Bytes::from_bytes_vec(bytes))
        .map_err(|e| err(format!("{e:?}")))?;
    let kept = optim.to_record().len();
    if kept != tensors.len() {
        return Err(err(format!(
            "{} of {} state tensors could not be restored (wrong shape or dtype)",
            tensors.len() - kept,
            tensors.len()
        )));
    }
    Ok(optim)
}

/// Prefix of the temporary directory a checkpoint is written into before its rename
/// (`.tmp-step-<step>-<pid>`).
const CHECKPOINT_TMP_PREFIX: &str = ".tmp-step-";

/// Whether process `pid` is alive (`kill(pid, 0)` succeeds or fails for lack of permission).
fn process_alive(pid: u32) -> bool {
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    if pid <= 0 {
        return false;
    }
    // SAFETY: signal 0 sends nothing; it only checks that the process exists.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Removes the checkpoint temporary directories `checkpoints/.tmp-step-<step>-<pid>` left by
/// processes that died while writing a checkpoint (kill -9, power loss). A directory of a live
/// process other than this one (another run writing into the same folder) is left alone.
/// Returns the removed directories.
pub fn remove_stale_checkpoint_temps(out: &Path) -> Result<Vec<PathBuf>> {
    let root = out.join("checkpoints");
    let mut removed = Vec::new();
    if !root.is_dir() {
        return Ok(removed);
    }
    let me = std::process::id();
    for e in std::fs::read_dir(&root).map_err(io_err(&root))? {
        let e = e.map_err(io_err(&root))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(CHECKPOINT_TMP_PREFIX) else {
            continue;
        };
        let Some(pid) = rest.rsplit('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if pid != me && process_alive(pid) {
            continue;
        }
        let path = e.path();
        std::fs::remove_dir_all(&path).map_err(io_err(&path))?;
        tracing::info!(
            "removed the stale checkpoint temporary {} (process {pid} is gone)",
            path.display()
        );
        removed.push(path);
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Temporaries of dead processes go, a live process's stays, other entries are untouched.
    #[test]
    fn stale_checkpoint_temporaries_of_dead_processes_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("checkpoints");
        let mut gone = std::process::Command::new("true").spawn().unwrap();
        let dead = gone.id();
        gone.wait().unwrap();
        // A live process that is not this one: a sleeping child.
        let mut live_child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let stale = root.join(format!(".tmp-step-00000007-{dead}"));
        let mine = root.join(format!(".tmp-step-00000008-{}", std::process::id()));
        let live = root.join(format!(".tmp-step-00000009-{}", live_child.id()));
        let other = root.join("step-00000006");
        for d in [&stale, &mine, &live, &other] {
            std::fs::create_dir_all(d).unwrap();
        }
        let removed = remove_stale_checkpoint_temps(dir.path()).unwrap();
        live_child.kill().unwrap();
        live_child.wait().unwrap();
        assert_eq!(removed.len(), 2, "{removed:?}");
        assert!(
            !stale.exists() && !mine.exists(),
            "this process has not started writing: its own name is stale too"
        );
        assert!(live.exists() && other.exists());
    }
}
