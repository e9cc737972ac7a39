//! Other renderers, driven for side-by-side measurements: Mitsuba 3 and Embree 4 run in a Python
//! process (`peers.py`, compiled in) that the benches talk to in JSON lines, so that each side
//! is loaded once and the two are timed alternately in one run.

use anyhow::{Context, Result, anyhow, bail};
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

const SCRIPT: &str = include_str!("peers.py");

/// How to install the peers, for the benches' "skipped" lines.
pub const INSTALL: &str = "python3 -m venv .venv-peers && .venv-peers/bin/pip install mitsuba==3.9.1 embreex numpy \
     pygltflib; apt-get install -y libllvm19; then pass --python .venv-peers/bin/python and set \
     DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so";

/// The Python process serving the peers, and a scratch folder for the files it exchanges.
pub struct Peers {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    dir: tempfile::TempDir,
}

impl Peers {
    /// Starts `python` on the peer script.
    pub fn start(python: &Path) -> Result<Peers> {
        let dir = tempfile::tempdir().context("creating a scratch folder for the peers")?;
        let script = dir.path().join("peers.py");
        std::fs::write(&script, SCRIPT)?;
        let mut child = Command::new(python)
            .arg("-u")
            .arg(&script)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting {}", python.display()))?;
        let stdin = child.stdin.take().expect("piped");
        let stdout = BufReader::new(child.stdout.take().expect("piped"));
        Ok(Peers { child, stdin, stdout, dir })
    }

    /// Starts the peers' process and checks that it can load `module` ("mitsuba" or "embreex"):
    /// its version, or why not (printed by the caller as a skip).
    pub fn with(python: &Path, module: &str) -> Result<(Peers, String), String> {
        let mut peers = Peers::start(python).map_err(|e| format!("{e:#}"))?;
        let answer = peers.request(json!({"op": "probe", "module": module})).map_err(|e| format!("{e:#}"))?;
        Ok((peers, answer["version"].as_str().unwrap_or("?").to_string()))
    }

    /// A path in the scratch folder.
    pub fn scratch(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Sends one request and reads its answer; an `error` answer is an error.
    pub fn request(&mut self, request: Value) -> Result<Value> {
        writeln!(self.stdin, "{request}").context("writing to the peers' process")?;
        let mut line = String::new();
        if self.stdout.read_line(&mut line).context("reading from the peers' process")? == 0 {
            bail!("the peers' process ended (its messages are above)");
        }
        let answer: Value = serde_json::from_str(&line).with_context(|| format!("the peers' answer {line:?}"))?;
        if let Some(e) = answer.get("error") {
            return Err(anyhow!("{}", e.as_str().unwrap_or("?")));
        }
        Ok(answer)
    }
}

impl Drop for Peers {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Writes `values` as little-endian f32.
pub fn write_f32(path: &Path, values: impl Iterator<Item = f32>) -> Result<()> {
    let bytes: Vec<u8> = values.flat_map(f32::to_le_bytes).collect();
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// Reads little-endian 4-byte words.
pub fn read_words(path: &Path) -> Result<Vec<[u8; 4]>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    Ok(bytes.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect())
}
