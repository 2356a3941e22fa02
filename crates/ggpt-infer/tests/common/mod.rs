//! Shared test setup: a tiny random-init network saved as burnpack and a tiny synthetic scene
//! with matches ([`save_tiny_weights`], [`tiny_scene`]); and running the repository's Python readers (`scripts/check_ply.py`, `scripts/check_colmap_model.py`)
//! from tests, with the convention of `crates/ggpt-sfm/tests/colmap_python.rs`: when `python3` or
//! the module is missing, the check is skipped with a loud warning on stderr, unless
//! `GGPT_REQUIRE_PYTHON_READERS=1` (set by CI), in which case the test fails.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// `scripts/NAME` of the workspace.
pub fn script(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../scripts")
        .join(name)
}

/// `true` when `python3 -c "import numpy, MODULE"` works. Otherwise fails the test under
/// `GGPT_REQUIRE_PYTHON_READERS=1`, or warns loudly (what was not checked) and returns `false`.
pub fn python_module_available(test: &str, module: &str, pip: &str, unchecked: &str) -> bool {
    let probe = Command::new("python3")
        .args(["-c", &format!("import numpy, {module}")])
        .output();
    let problem = match &probe {
        Ok(o) if o.status.success() => return true,
        Ok(o) => format!(
            "`python3 -c \"import numpy, {module}\"` failed: {}",
            String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
                .trim()
        ),
        Err(e) => format!("cannot run python3: {e}"),
    };
    if std::env::var("GGPT_REQUIRE_PYTHON_READERS").as_deref() == Ok("1") {
        panic!(
            "{test}: GGPT_REQUIRE_PYTHON_READERS=1 but {module} is not usable: {problem} (install it with `pip install {pip}`)"
        );
    }
    // written to the stderr handle directly: libtest's capture only intercepts `eprintln!`
    let bar = "!".repeat(88);
    let msg = format!(
        "\n{bar}\nWARNING: {test}: {module} check SKIPPED: {problem}\n         {unchecked} was NOT checked with {module} (pip install {pip};\n         set GGPT_REQUIRE_PYTHON_READERS=1 to make this a failure)\n{bar}\n"
    );
    let _ = std::io::Write::write_all(&mut std::io::stderr(), msg.as_bytes());
    false
}

/// Runs `python3 scripts/SCRIPT path`, asserts exit 0 and returns the printed JSON.
pub fn run_python_check(script_name: &str, path: &Path) -> serde_json::Value {
    let out = Command::new("python3")
        .arg(script(script_name))
        .arg(path)
        .output()
        .expect("running python3");
    assert!(
        out.status.success(),
        "{script_name} {} failed ({}):\nstdout: {}\nstderr: {}",
        path.display(),
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{script_name} printed no JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

/// Saves a freshly initialised `GgptConfig::tiny()` network (random weights) as burnpack at
/// `path`.
pub fn save_tiny_weights(path: &Path) {
    let device = ggpt_model::device::device_from_name("ndarray").unwrap();
    ggpt_model::weights::save_burnpack(
        &ggpt_model::Ggpt::new(&ggpt_model::GgptConfig::tiny(), &device),
        path,
    )
    .unwrap();
}

/// A 3-view 56 x 42 `ggpt-synth` room with simulated matches (no SfM result), from `seed`.
pub fn tiny_scene(seed: u64) -> ggpt_core::Scene {
    let cfg = ggpt_synth::SynthConfig {
        views: 3,
        width: 56,
        height: 42,
        seed,
        matches: true,
        ..ggpt_synth::SynthConfig::default()
    };
    ggpt_synth::generate(&cfg).unwrap().scene
}
