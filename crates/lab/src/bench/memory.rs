//! `tessera bench memory`: what a worker's memory holds for each scene of the suite, measured as
//! the peak resident size of a real `tessera render` of it, beside the estimate the coordinator
//! admits scenes by (`tessera_scene::Census::memory`). A farm's nodes fit as many workers as
//! their memory holds; an estimate below the measure would let a node be overcommitted.

use crate::bench::scaling::suite;
use anyhow::{Context, Result, bail};
use clap::Args;

#[derive(Args, Debug)]
pub struct MemoryBenchArgs {
    /// Scenes [default: the suite of `bench scaling`, and the Cornell box as the baseline].
    pub scenes: Vec<String>,
    /// Render threads of each measured process (each thread holds its own small buffers).
    #[arg(long, default_value_t = 2, env = "TESSERA_BENCH_THREADS")]
    pub threads: usize,
}

/// A process's peak resident bytes and how it ended.
struct Peak {
    bytes: u64,
    ok: bool,
}

pub fn memory(args: MemoryBenchArgs) -> Result<()> {
    let scenes = if args.scenes.is_empty() { suite(&[]) } else { args.scenes.clone() };
    let baseline_spec = "builtin:cornell-box";
    let dir = tempfile::tempdir()?;
    let threads = args.threads.max(1).to_string();
    let measure = |spec: &str| -> Result<Peak> {
        let out = dir.path().join("memory.exr");
        let flags = ["--width", "8", "--height", "8", "--spp", "1", "--quality", "fixed", "--threads", &threads, "-q"];
        let child = std::process::Command::new(std::env::current_exe()?)
            .args(["render", spec, "--out", out.to_str().context("a temporary path that is not UTF-8")?])
            .args(flags)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()?;
        peak_of(child)
    };
    let baseline = measure(baseline_spec)?;
    if !baseline.ok {
        bail!("the baseline render ({baseline_spec}) failed");
    }
    println!(
        "peak resident memory of `tessera render SCENE --width 8 --height 8 --spp 1 --threads {threads}`; the \
         Cornell box's {:.1} MiB is the process's own baseline (code, runtime, thread stacks)",
        mib(baseline.bytes)
    );
    println!("estimate: what the coordinator admits a scene by (Census::memory; --max-scene-memory)");
    println!(
        "{:<44} {:>10} {:>11} {:>10} {:>10} {:>10} {:>9}",
        "scene", "triangles", "texels", "peak MiB", "over base", "B/tri*", "estimate"
    );
    // Every render first, while this process is small: a child's peak counts the memory it
    // shared with this process before it ran the binary, so reading the scenes here first would
    // add to theirs.
    let peaks = scenes.iter().map(|spec| measure(spec)).collect::<Result<Vec<_>>>()?;
    for (spec, peak) in scenes.iter().zip(peaks) {
        let census = tessera_scene::open(spec).and_then(|s| s.census(None, None));
        let census = match census {
            Ok(c) => c,
            Err(e) => {
                println!("{spec}: cannot be read ({e})");
                continue;
            }
        };
        let name = spec.rsplit('/').next().unwrap_or(spec);
        if !peak.ok {
            println!("{name:<44} the render failed");
            continue;
        }
        let over = peak.bytes.saturating_sub(baseline.bytes);
        // Bytes per drawn triangle once the texels are taken at the estimate's own rate: the
        // figure to set `BYTES_PER_DRAWN_TRIANGLE` by, where a scene has enough triangles to say.
        let texel_bytes = census.texels * tessera_scene::BYTES_PER_TEXEL;
        let per_triangle = if census.drawn_triangles >= 10_000 {
            format!("{:.0}", over.saturating_sub(texel_bytes) as f64 / census.drawn_triangles as f64)
        } else {
            "-".into()
        };
        let estimate = census.memory();
        let verdict = if estimate >= over { "covers" } else { "UNDER" };
        println!(
            "{name:<44} {:>10} {:>11} {:>10.1} {:>10.1} {per_triangle:>10} {:>6.1} MiB {verdict}",
            census.drawn_triangles,
            census.texels,
            mib(peak.bytes),
            mib(over),
            mib(estimate)
        );
    }
    println!(
        "* B/tri: (over base - texels x {} B) / triangles, for scenes of 10,000 triangles or more; the estimate takes {} B a \
         triangle and {} B a texel",
        tessera_scene::BYTES_PER_TEXEL,
        tessera_scene::BYTES_PER_DRAWN_TRIANGLE,
        tessera_scene::BYTES_PER_TEXEL
    );
    println!("  and {} MiB a scene", tessera_scene::BYTES_PER_SCENE >> 20);
    Ok(())
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

/// Waits for `child` and reads its own peak resident size (`wait4`'s `ru_maxrss`; the whole
/// process tree's `RUSAGE_CHILDREN` would give the largest child so far, not this one's).
#[cfg(unix)]
fn peak_of(child: std::process::Child) -> Result<Peak> {
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: `pid` is our own unwaited child; `status` and `usage` are valid for writes.
    let waited = unsafe { libc::wait4(pid, &mut status, 0, usage.as_mut_ptr()) };
    if waited != pid {
        bail!("waiting for the render process: {}", std::io::Error::last_os_error());
    }
    // SAFETY: wait4 succeeded, so it filled `usage`.
    let usage = unsafe { usage.assume_init() };
    // Linux reports ru_maxrss in KiB.
    Ok(Peak { bytes: usage.ru_maxrss as u64 * 1024, ok: libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0 })
}

#[cfg(not(unix))]
fn peak_of(_child: std::process::Child) -> Result<Peak> {
    bail!("bench memory reads a process's peak memory with wait4, which this system lacks")
}
