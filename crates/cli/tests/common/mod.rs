//! Helpers shared by the end-to-end tests (a module of `tests/e2e.rs`).
#![allow(dead_code)]

pub mod farm;

use std::net::TcpListener;
use std::path::{Path, PathBuf};

/// A fresh, empty directory for one test: `<tmp>/tessera-<suite>-<pid>-<name>`. It is removed
/// when the test passes; a failing test keeps it (and says where) so its logs can be read.
pub struct Scratch(PathBuf);

pub fn scratch(suite: &str, name: &str) -> Scratch {
    let dir = std::env::temp_dir().join(format!("tessera-{suite}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    Scratch(dir)
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<std::ffi::OsStr> for Scratch {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.0.as_os_str()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept {} for inspection", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A loopback port nobody listens on right now. Another process may take it before the test
/// binds it: where a process can be started on port 0, start it so and read its port with
/// [`port_in_log`] instead.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The port `child` says it listens on in the first line of `log` (its standard error) that
/// starts with `says` (`coordinator listening on`, `dashboard on`, `metrics on`): the address
/// follows, with or without a scheme. Waits up to 60 s; fails with the log if the process exits
/// first (its port taken, a bad flag) or never says it.
pub fn port_in_log(child: &mut std::process::Child, log: &Path, says: &str) -> u16 {
    let start = std::time::Instant::now();
    loop {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        let line = text.lines().find_map(|l| l.strip_prefix(says));
        let port = line.map(|rest| {
            let addr = rest.trim_start();
            let addr = addr.split_once("://").map_or(addr, |(_, a)| a);
            let addr = addr.split(['/', ' ']).next().unwrap_or_default();
            let port = addr.rsplit_once(':').and_then(|(_, p)| p.parse::<u16>().ok());
            port.unwrap_or_else(|| panic!("no port in '{says}{rest}'"))
        });
        if let Some(port) = port {
            return port;
        }
        if let Ok(Some(status)) = child.try_wait() {
            panic!("the process exited ({status}) before saying '{says}':\n{text}");
        }
        assert!(start.elapsed() < std::time::Duration::from_secs(60), "no '{says}' within 60 s:\n{text}");
        std::thread::sleep(std::time::Duration::from_millis(25));
    }
}

/// Every channel of the two images, bit for bit (the headers differ in the scene's name).
pub fn assert_same_pixels(a: &Path, b: &Path) {
    let (x, y) = (tessera_film::read_exr(a).unwrap(), tessera_film::read_exr(b).unwrap());
    assert_eq!((x.width, x.height), (y.width, y.height));
    let bits = |img: &tessera_film::ExrImage| -> Vec<u32> {
        img.rgb
            .iter()
            .flatten()
            .chain(img.variance.iter().flatten())
            .chain(&img.spp)
            .chain(&img.emitter)
            .map(|v| v.to_bits())
            .collect()
    };
    assert!(bits(&x) == bits(&y), "{} and {} differ", a.display(), b.display());
    // The feature layers too, where either has them (their values are finite: == is bitwise here).
    assert!(x.features == y.features, "the feature layers of {} and {} differ", a.display(), b.display());
}

/// A child process killed when dropped, so a failing test leaves nothing running.
pub struct Proc(pub std::process::Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Proc {
    pub fn signal(&self, sig: &str) {
        let ok = std::process::Command::new("kill").args([sig, &self.0.id().to_string()]).status().unwrap().success();
        assert!(ok, "kill {sig} failed");
    }
}
