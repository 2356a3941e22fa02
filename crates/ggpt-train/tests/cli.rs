//! `ggpt-train` from the command line: the embedded default run, export with a strict reload,
//! a chunk set from an official per-sequence directory, and a corrupt shard.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ggpt_model::infer::infer_chunks;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_train::chunkset::{ChunkSet, Split};
use ggpt_train::trainer::{MetricsLine, list_checkpoints, load_checkpoint};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_ggpt-train"));
    c.env("RUST_LOG", "warn");
    c
}

fn run_ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("spawn ggpt-train");
    assert!(
        out.status.success(),
        "ggpt-train failed: {}\nstdout: {}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    out
}

/// `ggpt-train prepare` of a small synthetic chunk set (`train` training scenes, one val scene,
/// 3 views at 98x70) into `dir/set`.
fn prepare_small_set(dir: &Path, train: usize) -> PathBuf {
    let set_dir = dir.join("set");
    let train = train.to_string();
    run_ok(
        bin()
            .args(["prepare", "--out"])
            .arg(&set_dir)
            .args([
                "--synthetic-train",
                &train,
                "--synthetic-val",
                "1",
                "--views",
                "3",
                "--width",
                "98",
                "--height",
                "70",
            ])
            .args([
                "--chunks-per-scene",
                "2",
                "--max-pixels",
                "1500",
                "--min-dlt",
                "20",
                "--min-pixels",
                "200",
            ]),
    );
    set_dir
}

fn official_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/fixtures/official_format/synth_room_s0")
}

#[allow(deprecated)]
fn cpu() -> burn::tensor::Device {
    burn::tensor::Device::ndarray()
}

/// No arguments: a synthetic chunk set is prepared and the tiny configuration trained for 20
/// steps with validation and checkpoints; `export` writes official safetensors that load
/// strictly and reproduce the checkpoint's outputs.
#[test]
fn default_run_then_export_reloads_strictly() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_ok(bin().arg("--out").arg(dir.path()));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("trained 20 steps"), "{stdout}");
    assert!(stdout.contains("held-out chunks: AUC@5"), "{stdout}");
    let run = dir.path().join("run");
    let steps: Vec<u64> = list_checkpoints(&run)
        .unwrap()
        .iter()
        .map(|(s, _)| *s)
        .collect();
    assert_eq!(steps, vec![10, 20]);
    let lines: Vec<MetricsLine> = std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.iter().filter(|l| l.kind == "train").count(), 20);
    assert_eq!(lines.iter().filter(|l| l.kind == "val").count(), 2);
    assert!(lines.iter().all(|l| l.loss.is_finite()));

    let export = dir.path().join("export");
    run_ok(
        bin()
            .args(["export", "--checkpoint"])
            .arg(&run)
            .arg("--out-dir")
            .arg(&export),
    );
    let cfg = GgptConfig::from_json_file(&export.join("model_config.json")).unwrap();
    assert_eq!(cfg, GgptConfig::tiny());
    let device = cpu();
    let exported = ggpt_model::weights::load_checkpoint(
        Ggpt::new(&cfg, &device),
        &export.join("model.safetensors"),
    )
    .unwrap();
    let (ckpt, _, state) =
        load_checkpoint(&run.join("checkpoints/step-00000020"), &device).unwrap();
    assert_eq!(state.step, 20);
    let set = ChunkSet::open(&dir.path().join("chunkset")).unwrap();
    let val = set.load_split(Split::Val).unwrap();
    let input = [val[0].to_input()];
    use burn::module::Module;
    let a = infer_chunks(&exported, &cfg, &input, &device).unwrap();
    let b = infer_chunks(&ckpt.valid(), &cfg, &input, &device).unwrap();
    assert_eq!(a[0].ff_pts_out, b[0].ff_pts_out);
    assert_eq!(a[0].ff_pts_conf_out, b[0].ff_pts_conf_out);
    // training moved the outputs away from the zero-initialised head's identity
    assert!(
        a[0].ff_pts_out
            .iter()
            .zip(&val[0].ff_pts)
            .any(|(o, i)| o != i)
    );
    // the training sampler travels with the model
    let inf: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(export.join("inference.json")).unwrap())
            .unwrap();
    assert_eq!(
        inf["chunking"],
        serde_json::json!({"chunk_size": 0.2, "max_pixels": 1500, "min_dlt": 20, "min_pixels": 200})
    );

    // chunk-level validation of the exported folder on the recorded val chunks
    let out = run_ok(
        bin()
            .args(["eval", "--model"])
            .arg(&export)
            .arg("--data")
            .arg(dir.path().join("chunkset"))
            .args(["--chunk-level", "2"]),
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("2 val chunks: AUC@5 input"), "{text}");

    // whole-scene evaluation of the exported folder on a fresh synthetic scene, sampler from
    // inference.json except the flag given
    let report = dir.path().join("eval.json");
    let out = run_ok(
        bin()
            .args(["eval", "--model"])
            .arg(&export)
            .args([
                "--synthetic-scenes",
                "1",
                "--first-seed",
                "77",
                "--views",
                "3",
                "--width",
                "98",
                "--height",
                "70",
                "--min-dlt",
                "25",
                "--out",
            ])
            .arg(&report),
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("mean over 1 held-out scenes"));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(r["summary"]["scenes"], 1);
    assert_eq!(r["chunking"]["max_pixels"], 1500);
    assert_eq!(r["chunking"]["min_dlt"], 25);
    let scene = &r["scenes"][0];
    assert!(scene["chunks"].as_u64().unwrap() > 0, "{scene}");
    for k in ["ff_auc5", "refined_auc5", "ff_auc10", "refined_auc10"] {
        let v = scene[k].as_f64().unwrap();
        assert!((0.0..=100.0).contains(&v), "{k} = {v}");
    }
}

/// `prepare --official DIR`: chunks from the official per-sequence files, GT aligned into the
/// SfM frame (the dense points and the GT agree to a fraction of the chunk size).
#[test]
fn prepare_from_an_official_directory() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = dir.path().join("set");
    let out = run_ok(
        bin()
            .args(["prepare", "--out"])
            .arg(&set_dir)
            .arg("--official")
            .arg(official_dir())
            .args([
                "--val-fraction",
                "0",
                "--chunks-per-scene",
                "3",
                "--max-pixels",
                "1200",
                "--min-dlt",
                "40",
                "--min-pixels",
                "300",
            ]),
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("1 scenes"));
    let set = ChunkSet::open(&set_dir).unwrap();
    let scene = &set.manifest.scenes[0];
    assert_eq!(
        (scene.views, scene.height, scene.width, scene.split),
        (4, 42, 56, Split::Train)
    );
    assert!(matches!(
        scene.source,
        ggpt_train::scene_source::SceneSource::Official(_)
    ));
    assert!(scene.metres_per_unit.is_finite() && scene.metres_per_unit > 0.0);
    let chunks = set.load_split(Split::Train).unwrap();
    assert_eq!(chunks.len(), 3);
    for c in &chunks {
        c.validate().unwrap();
        assert!(c.len() <= 1200 && c.geo_msk.iter().filter(|&&m| m).count() >= 40);
        let mut d: Vec<f32> = c
            .ff_pts
            .iter()
            .zip(&c.gt_pts)
            .zip(&c.gt_msk)
            .filter(|(_, m)| **m)
            .map(|((a, b), _)| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .collect();
        assert!(!d.is_empty());
        d.sort_by(f32::total_cmp);
        assert!(
            d[d.len() / 2] < 0.5,
            "median |ff - gt| = {} chunk units",
            d[d.len() / 2]
        );
    }
    // a directory without gt.bin is refused with its path
    let no_gt = dir.path().join("no_gt");
    std::fs::create_dir_all(&no_gt).unwrap();
    for f in ["ff_outputs.bin", "sfm_dlt_outputs.bin"] {
        std::fs::copy(official_dir().join(f), no_gt.join(f)).unwrap();
    }
    let out = bin()
        .args(["prepare", "--out"])
        .arg(dir.path().join("set2"))
        .arg("--official")
        .arg(&no_gt)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no_gt") && err.contains("gt.bin"), "{err}");
}

/// A truncated training shard stops `train` with an error naming the shard (no silent skip).
#[test]
fn truncated_shard_stops_training_naming_the_shard() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = prepare_small_set(dir.path(), 1);
    let set = ChunkSet::open(&set_dir).unwrap();
    let shard = set
        .manifest
        .shards
        .iter()
        .find(|s| s.split == Split::Train)
        .unwrap();
    let path = set_dir.join(&shard.file);
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let out = bin()
        .args(["train", "--data"])
        .arg(&set_dir)
        .arg("--out")
        .arg(dir.path().join("run"))
        .args(["--config", "tiny", "--steps", "2"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(&shard.file), "{err}");
    assert!(
        !dir.path().join("run/checkpoints").exists(),
        "no checkpoint from corrupt data"
    );
}

/// `--devices cpu,cpu --grad-accum 2` trains, records the replicas and the BatchNorm batching
/// in `config.json` and the checkpoint, and a batch smaller than replicas x micro-batches is a
/// clear error.
#[test]
fn two_replicas_with_gradient_accumulation_train_and_are_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = prepare_small_set(dir.path(), 2);
    let run = dir.path().join("run");
    run_ok(
        bin()
            .args(["train", "--data"])
            .arg(&set_dir)
            .arg("--out")
            .arg(&run)
            .args([
                "--config",
                "tiny",
                "--steps",
                "2",
                "--batch-size",
                "4",
                "--devices",
                "cpu,cpu",
                "--grad-accum",
                "2",
                "--val-every",
                "0",
            ]),
    );
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["replicas"], serde_json::json!(["cpu", "cpu"]));
    assert_eq!(cfg["grad_accum"], 2);
    assert!(
        cfg["batchnorm"]
            .as_str()
            .unwrap()
            .contains("2 replica(s) x 2 micro-batch(es)"),
        "{}",
        cfg["batchnorm"]
    );
    assert_eq!(train_losses(&run).len(), 2);
    let state: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(run.join("checkpoints/step-00000002/state.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        state["options"]["devices"],
        serde_json::json!(["cpu", "cpu"])
    );
    let out = bin()
        .args(["train", "--data"])
        .arg(&set_dir)
        .arg("--out")
        .arg(dir.path().join("run2"))
        .args([
            "--config",
            "tiny",
            "--steps",
            "1",
            "--batch-size",
            "2",
            "--devices",
            "cpu,cpu",
            "--grad-accum",
            "2",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--batch-size 2 is smaller than 2 replica(s) x --grad-accum 2"),
        "{err}"
    );
}

/// `--help` documents every flag of `train` (each long flag has a description).
#[test]
fn help_documents_the_flags() {
    let out = run_ok(bin().args(["train", "--help"]));
    let text = String::from_utf8_lossy(&out.stdout);
    for flag in [
        "--data",
        "--out",
        "--preset",
        "--model-config",
        "--steps",
        "--batch-size",
        "--lr",
        "--lr-schedule",
        "--clip-grad-norm",
        "--seed",
        "--save-every",
        "--resume",
        "--weights",
        "--devices",
        "--grad-accum",
        "--bn-momentum",
        "--device",
    ] {
        assert!(text.contains(flag), "{flag} missing from train --help");
    }
    // the old spellings are hidden aliases (docs/inference.md, flag changes)
    for old in ["--config ", "--init-from "] {
        assert!(
            !text.lines().any(|l| l.trim_start().starts_with(old)),
            "{old} shown in train --help"
        );
    }
}

fn train_losses(run: &Path) -> Vec<(u64, f64)> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<MetricsLine>(l).unwrap())
        .filter(|l| l.kind == "train")
        .map(|l| (l.step, l.loss))
        .collect()
}

/// A real child process killed with SIGKILL mid-run, then the documented
/// `train --data D --out O --resume --steps N` (bare `--resume` before another flag): the
/// resumed run reproduces the uninterrupted run's losses exactly, `metrics.jsonl` lists every
/// step once, and the checkpoint temporaries of dead processes are removed (a live process's is
/// kept).
#[test]
fn kill_9_then_bare_resume_reproduces_the_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = prepare_small_set(dir.path(), 2);
    let common = [
        "--config",
        "tiny",
        "--batch-size",
        "2",
        "--save-every",
        "2",
        "--val-every",
        "0",
        "--lr-schedule",
        "constant",
        "--device",
        "cpu",
    ];
    // The run to kill: many steps, killed once it is past its second checkpoint.
    let killed = dir.path().join("killed");
    let mut child = bin()
        .args(["train", "--data"])
        .arg(&set_dir)
        .arg("--out")
        .arg(&killed)
        .args(common)
        .args(["--steps", "1000"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    loop {
        let newest = list_checkpoints(&killed)
            .unwrap()
            .last()
            .map(|(s, _)| *s)
            .unwrap_or(0);
        if newest >= 4 {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the training child exited early"
        );
        assert!(
            t0.elapsed().as_secs() < 600,
            "no checkpoint at step 4 after 10 minutes"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let ckpt = list_checkpoints(&killed)
        .unwrap()
        .last()
        .map(|(s, _)| *s)
        .unwrap();
    let steps = ckpt + 3;
    // Leftovers: a temporary of a dead process (a finished child's pid), one of a live one.
    let mut gone = Command::new("true").spawn().unwrap();
    let dead_pid = gone.id();
    gone.wait().unwrap();
    let stale = killed.join(format!("checkpoints/.tmp-step-00000099-{dead_pid}"));
    let live = killed.join(format!(
        "checkpoints/.tmp-step-00000098-{}",
        std::process::id()
    ));
    for d in [&stale, &live] {
        std::fs::create_dir_all(d).unwrap();
        std::fs::write(d.join("model.bpk"), b"partial").unwrap();
    }
    let steps_s = steps.to_string();
    // CPU-only runs touch no GPU API: no Vulkan/wayland probe message, even without XDG_RUNTIME_DIR.
    let out = run_ok(
        bin()
            .env_remove("XDG_RUNTIME_DIR")
            .args(["train", "--data"])
            .arg(&set_dir)
            .arg("--out")
            .arg(&killed)
            .args(common)
            .args(["--resume", "--steps", &steps_s]),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !err.contains("XDG_RUNTIME_DIR"),
        "a CPU run probed a GPU device: {err}"
    );
    assert!(
        !stale.exists(),
        "the dead process's checkpoint temporary was not removed"
    );
    assert!(
        live.exists(),
        "a live process's checkpoint temporary must be left alone"
    );
    let reference = dir.path().join("reference");
    run_ok(
        bin()
            .args(["train", "--data"])
            .arg(&set_dir)
            .arg("--out")
            .arg(&reference)
            .args(common)
            .args(["--steps", &steps_s]),
    );
    let (a, b) = (train_losses(&reference), train_losses(&killed));
    assert_eq!(
        a.iter().map(|(s, _)| *s).collect::<Vec<_>>(),
        (1..=steps).collect::<Vec<_>>()
    );
    assert_eq!(
        b, a,
        "resumed after kill -9 (checkpoint {ckpt}) vs uninterrupted"
    );
    // `--resume` at the end of the line is accepted too (nothing left to do: the run is complete).
    run_ok(
        bin()
            .args(["train", "--data"])
            .arg(&set_dir)
            .arg("--out")
            .arg(&killed)
            .args(common)
            .args(["--steps", &steps_s, "--resume"]),
    );
    assert_eq!(train_losses(&killed), a);
}

/// SIGTERM (as Ctrl-C) stops a training run cleanly through the `ctrlc` handler: the process
/// finishes its step, writes a checkpoint of that step, says so and exits with success; the
/// checkpoint loads.
#[test]
fn sigterm_stops_training_with_a_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = prepare_small_set(dir.path(), 2);
    let out_dir = dir.path().join("run");
    let child = bin()
        .args(["train", "--data"])
        .arg(&set_dir)
        .arg("--out")
        .arg(&out_dir)
        .args([
            "--preset",
            "tiny",
            "--batch-size",
            "2",
            "--save-every",
            "1000",
        ])
        .args(["--val-every", "0", "--steps", "100000", "--device", "cpu"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // wait for a few training steps in metrics.jsonl
    let metrics = out_dir.join("metrics.jsonl");
    let t0 = std::time::Instant::now();
    while std::fs::read_to_string(&metrics).map_or(0, |t| t.lines().count()) < 3 {
        assert!(
            t0.elapsed().as_secs() < 600,
            "no training step after 10 minutes"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let pid = libc::pid_t::try_from(child.id()).unwrap();
    // SAFETY: plain kill(2) of our own child process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "exit {:?}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("interrupted at step"), "{stdout}");
    let (step, ckpt) = list_checkpoints(&out_dir).unwrap().last().cloned().unwrap();
    assert!((3..100_000).contains(&step), "checkpoint at step {step}");
    assert!(stdout.contains(&ckpt.display().to_string()), "{stdout}");
    load_checkpoint(
        &ckpt,
        &ggpt_model::device::device_from_name("cpu")
            .unwrap()
            .autodiff(),
    )
    .unwrap();
}
