//! The deployment paths as users take them: the README's local walkthrough, run as written, and
//! the Slurm script on one machine with stand-ins for `srun` and `scontrol`. Each script runs in
//! its own process group, killed whole if the test fails, so nothing is left running.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn bin_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_tessera")).parent().unwrap().to_path_buf()
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

use crate::common;
use common::{assert_same_pixels, free_port};

fn scratch(name: &str) -> common::Scratch {
    common::scratch("deploy", name)
}

/// A bash script and everything it starts, killed together when dropped.
struct Script(Child);

impl Drop for Script {
    fn drop(&mut self) {
        let _ = Command::new("kill").args(["-KILL", "--", &format!("-{}", self.0.id())]).status();
        let _ = self.0.wait();
    }
}

/// Runs `script` with bash in `dir`; returns (success, stdout, stderr).
fn run_bash(script: &str, dir: &Path, env: &[(&str, String)], timeout: Duration) -> (bool, String, String) {
    let (out, err) = (dir.join("script.out"), dir.join("script.err"));
    let mut cmd = Command::new("bash");
    cmd.arg("-c")
        .arg(script)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap())
        .process_group(0);
    for (k, _) in std::env::vars().filter(|(k, _)| k.starts_with("TESSERA_") || k.starts_with("SLURM_")) {
        cmd.env_remove(k);
    }
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut script_proc = Script(cmd.spawn().unwrap());
    let start = Instant::now();
    let status = loop {
        if let Some(status) = script_proc.0.try_wait().unwrap() {
            break Some(status);
        }
        if start.elapsed() > timeout {
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let read = |p: &Path| std::fs::read_to_string(p).unwrap_or_default();
    let (stdout, stderr) = (read(&out), read(&err));
    assert!(status.is_some(), "the script ran past {timeout:?}\nstdout:\n{stdout}\nstderr:\n{stderr}");
    (status.unwrap().success(), stdout, stderr)
}

fn path_with(first: &[&Path]) -> String {
    let mut parts: Vec<String> = first.iter().map(|p| p.display().to_string()).collect();
    parts.push(std::env::var("PATH").unwrap_or_default());
    parts.join(":")
}

/// The README's block between `<!-- walkthrough: local -->` and `<!-- /walkthrough -->`.
fn readme_walkthrough() -> String {
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let start = readme.find("<!-- walkthrough: local -->").expect("README has the local walkthrough marker");
    let end = readme[start..].find("<!-- /walkthrough -->").expect("README closes the walkthrough") + start;
    let block = &readme[start..end];
    let code_start = block.find("```sh\n").expect("a sh code block") + "```sh\n".len();
    let code_end = block[code_start..].find("```").expect("the code block ends") + code_start;
    block[code_start..code_end].to_string()
}

#[test]
fn readme_local_walkthrough() {
    let walkthrough = readme_walkthrough();
    assert!(walkthrough.lines().any(|l| l.starts_with("tessera coordinator")), "{walkthrough}");
    // The build line is the one step the harness has done already: the binary under test goes on
    // the PATH instead. Every other line runs as written.
    let script: String =
        walkthrough
            .lines()
            .map(|l| {
                if l.starts_with("cargo ") {
                    format!("export PATH=\"{}:$PATH\"", bin_dir().display())
                } else {
                    l.into()
                }
            })
            .collect::<Vec<_>>()
            .join("\n");
    let dir = scratch("walkthrough");
    let port = free_port();
    // The walkthrough uses the default address; another port keeps parallel tests apart.
    let env =
        [("TESSERA_LISTEN", format!("127.0.0.1:{port}")), ("TESSERA_COORDINATOR", format!("http://127.0.0.1:{port}"))];
    let (ok, stdout, stderr) =
        run_bash(&format!("set -euo pipefail\n{script}\n"), &dir, &env, Duration::from_secs(300));
    assert!(ok, "the walkthrough failed\nstdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(dir.join("farm-data/tessera.db").exists(), "the coordinator kept its data where the README says");
    assert!(dir.join("farm.png").exists());
    assert_same_pixels(&dir.join("farm.exr"), &dir.join("local.exr"));
    assert!(stdout.contains("rmse 0.000000"), "{stdout}");
    assert!(stderr.contains("coordinator stopped"), "the coordinator did not stop gracefully:\n{stderr}");
    assert!(std::net::TcpStream::connect(("127.0.0.1", port)).is_err(), "the coordinator is still listening");
}

#[test]
fn slurm_script_on_one_machine() {
    let dir = scratch("slurm");
    let stubs = dir.join("stubs");
    std::fs::create_dir_all(&stubs).unwrap();
    // srun: run the command once, here, dropping srun's own options; scontrol: one node.
    let srun = "#!/bin/sh\nwhile [ $# -gt 0 ]; do case \"$1\" in --*) shift;; *) break;; esac; done\nexec \"$@\"\n";
    let scontrol = "#!/bin/sh\necho localhost\n";
    for (name, text) in [("srun", srun), ("scontrol", scontrol)] {
        let p = stubs.join(name);
        std::fs::write(&p, text).unwrap();
        Command::new("chmod").arg("+x").arg(&p).status().unwrap();
    }
    let port = free_port();
    let env = [
        ("PATH", path_with(&[&stubs, &bin_dir()])),
        ("SLURM_JOB_ID", "7".to_string()),
        ("SLURM_JOB_NODELIST", "localhost".to_string()),
        ("TESSERA_SLURM_PORT", port.to_string()),
        ("TESSERA_THREADS", "2".to_string()),
    ];
    let script = repo().join("deploy/slurm/tessera.sbatch");
    let args = "builtin:cornell-box slurm.exr --width 48 --height 32 --spp 32 --seed 3";
    let (ok, stdout, stderr) =
        run_bash(&format!("bash {} {args}", script.display()), &dir, &env, Duration::from_secs(300));
    assert!(ok, "the sbatch script failed\nstdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stdout.contains("wrote slurm.exr"), "{stdout}");
    assert!(dir.join("tessera-data-7/tessera.db").exists());
    let local = dir.join("local.exr");
    let o = Command::new(env!("CARGO_BIN_EXE_tessera"))
        .args(["render", "builtin:cornell-box", "--width", "48", "--height", "32", "--spp", "32", "--seed", "3", "-q"])
        .arg("--out")
        .arg(&local)
        .output()
        .unwrap();
    assert!(o.status.success());
    assert_same_pixels(&dir.join("slurm.exr"), &local);
    assert!(stderr.contains("coordinator stopped"), "{stderr}");
    assert!(std::net::TcpStream::connect(("127.0.0.1", port)).is_err(), "the coordinator is still listening");
}

#[test]
fn the_templates_placeholder_token_is_refused() {
    let secret = std::fs::read_to_string(repo().join("deploy/k8s/secret.yaml")).unwrap();
    let placeholder = secret.lines().find_map(|l| l.trim().strip_prefix("TESSERA_TOKEN: ")).unwrap().trim();
    let dir = scratch("placeholder");
    let o = Command::new(env!("CARGO_BIN_EXE_tessera"))
        .args(["coordinator", "--listen", "127.0.0.1:0"])
        .arg("--data-dir")
        .arg(dir.join("data"))
        .env("TESSERA_TOKEN", placeholder)
        .output()
        .unwrap();
    assert!(!o.status.success(), "the coordinator started with the template's token");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("placeholder"), "{stderr}");
}
