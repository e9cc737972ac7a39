//! A local render's exact sums, kept beside its image (`tessera render --keep-sums` writes
//! NAME.sums) so that `tessera render --refine NAME.exr` can go on from it to a lower target
//! error or more samples: only the passes those add are rendered, and the image is the bits of
//! a render with them from the start (`tessera_local::render_film_from`). A farm keeps its
//! results in its store instead (`tessera refine ID`).
//!
//! The file: a marker line, the scene's hash and the render's setup (its settings, environment,
//! pose and variant: what its pixels depend on besides the samples), its samples per pixel and
//! adaptive target, then each tile of the plan with its passes and its sums in the wire's exact
//! encoding (`tessera_proto::sums`), which a reader checks as a coordinator checks a worker's.

use anyhow::{Context, Result, bail};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use tessera_film::Film;
use tessera_local::options::Sampling;
use tessera_local::{Finished, Rendered};
use tessera_proto::sums::{MAX_PIXEL_BYTES_WITH_FEATURES, decode_tile_sums, encode_tile_sums};
use tessera_render::plan::{PASS_SPP, RenderPlan, TILE_SIZE};
use tessera_request::{Adaptive, Setup};

const MARKER: &[u8] = b"tessera sums 1\n";
/// Most bytes of the setup's encoding a file may hold (an environment map travels by hash).
const MAX_SETUP_BYTES: u64 = 1 << 20;

/// Where the sums of the image at `exr` are kept.
pub fn path_for(exr: &Path) -> PathBuf {
    exr.with_extension("sums")
}

/// What a kept render was: the scene's hash, its setup and samples, and what it rendered.
pub struct Kept {
    pub scene_hash: String,
    pub setup: Setup,
    pub sampling: Sampling,
    pub finished: Finished,
}

/// Writes a whole render's sums to `path`, tile by tile (through a temporary file, renamed when
/// complete).
pub fn write(path: &Path, scene_hash: &str, setup: &Setup, sampling: Sampling, rendered: &Rendered) -> Result<()> {
    let s = &setup.settings;
    let plan = RenderPlan::new(s.width, s.height, TILE_SIZE, sampling.spp, PASS_SPP);
    let partial = path.with_extension("sums.partial");
    let file = std::fs::File::create(&partial).with_context(|| format!("creating {}", partial.display()))?;
    let mut out = std::io::BufWriter::new(file);
    let put = || -> std::io::Result<()> {
        out.write_all(MARKER)?;
        for field in [scene_hash.as_bytes(), &setup.encode()] {
            out.write_all(&(field.len() as u64).to_le_bytes())?;
            out.write_all(field)?;
        }
        let (target, min_spp) = sampling.adaptive.map_or((0.0, 0), |a| (a.target_error, a.min_spp));
        out.write_all(&sampling.spp.to_le_bytes())?;
        out.write_all(&target.to_le_bytes())?;
        out.write_all(&min_spp.to_le_bytes())?;
        for (tile, passes) in plan.tiles.iter().zip(&rendered.passes) {
            let sums = encode_tile_sums(&rendered.film.tile_sums(*tile));
            out.write_all(&passes.to_le_bytes())?;
            out.write_all(&(sums.len() as u64).to_le_bytes())?;
            out.write_all(&sums)?;
        }
        out.into_inner().map_err(|e| e.into_error())?.sync_all()
    };
    put().with_context(|| format!("writing {}", partial.display()))?;
    std::fs::rename(&partial, path).with_context(|| format!("renaming {} to {}", partial.display(), path.display()))
}

/// Reads the sums kept for the image at `exr`, for a render of `width` x `height` (which bounds
/// what is read): every tile's sums checked, and its pixels holding exactly its passes' samples.
pub fn read(exr: &Path, width: u32, height: u32) -> Result<Kept> {
    let path = path_for(exr);
    let file = std::fs::File::open(&path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => anyhow::anyhow!(
            "{} has no sums kept beside it ({}): only a render made with --keep-sums can be refined",
            exr.display(),
            path.display()
        ),
        _ => anyhow::Error::new(e).context(format!("opening {}", path.display())),
    })?;
    let pixels = width as u64 * height as u64;
    let most = 4096 + MAX_SETUP_BYTES + pixels * MAX_PIXEL_BYTES_WITH_FEATURES as u64 + pixels * 16;
    // Read from the file opened, at most one byte past the bound (so that a file longer than
    // it, or growing, is refused without being read whole).
    let mut bytes = Vec::new();
    file.take(most + 1).read_to_end(&mut bytes).with_context(|| format!("reading {}", path.display()))?;
    if bytes.len() as u64 > most {
        bail!(
            "{} is more than the {most} bytes sums of a {width} x {height} image take: is it another render's?",
            path.display()
        );
    }
    parse(&bytes).with_context(|| format!("{} is not sums tessera kept, or is damaged", path.display()))
}

/// The bytes of a kept file, read front to back.
struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: u64) -> Result<&'a [u8]> {
        let n = usize::try_from(n).ok().filter(|&n| n <= self.0.len()).context("it ends early")?;
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }

    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into()?))
    }

    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into()?))
    }
}

fn parse(bytes: &[u8]) -> Result<Kept> {
    let mut r = Reader(bytes.strip_prefix(MARKER).context("no marker line")?);
    let hash_len = r.u64()?;
    if hash_len > 128 {
        bail!("a scene hash of {hash_len} bytes");
    }
    let scene_hash = String::from_utf8(r.take(hash_len)?.to_vec()).context("the scene's hash")?;
    let setup_len = r.u64()?;
    if setup_len > MAX_SETUP_BYTES {
        bail!("a setup of {setup_len} bytes");
    }
    let setup = Setup::decode(r.take(setup_len)?).map_err(|e| anyhow::anyhow!("the setup: {e}"))?;
    let spp = r.u32()?;
    let target_error = f32::from_bits(r.u32()?);
    let min_spp = r.u32()?;
    let adaptive = (target_error > 0.0).then_some(Adaptive { target_error, min_spp });
    let s = &setup.settings;
    if spp == 0 || spp > tessera_request::limits::MAX_SPP {
        bail!("{spp} samples per pixel");
    }
    let plan = RenderPlan::new(s.width, s.height, TILE_SIZE, spp, PASS_SPP);
    let mut film = Film::with_features(s.width, s.height, s.features);
    let mut passes = Vec::with_capacity(plan.tiles.len());
    for tile in &plan.tiles {
        let n = r.u32()?;
        if n > plan.passes_per_tile() {
            bail!("a tile of {n} passes, of at most {}", plan.passes_per_tile());
        }
        let len = r.u64()?;
        let sums = decode_tile_sums(r.take(len)?).map_err(|e| anyhow::anyhow!("a tile's sums: {e}"))?;
        let samples = plan.samples(0, n).len() as u64;
        if sums.tile != *tile || sums.pixels.iter().any(|p| p.n + p.dropped != samples) {
            bail!("tile ({}, {}) does not hold its {n} passes' samples", tile.x0, tile.y0);
        }
        film.merge_tile(&sums).map_err(|e| anyhow::anyhow!("a tile's sums: {e}"))?;
        passes.push(n);
    }
    if !r.0.is_empty() {
        bail!("{} bytes follow the last tile", r.0.len());
    }
    Ok(Kept { scene_hash, setup, sampling: Sampling { spp, adaptive }, finished: Finished { film, passes } })
}

/// Checks that `kept` may go on to `sampling` under `setup` (of the scene hashed `scene_hash`)
/// to the bits of a render with them from the start, saying what to change where it may not.
pub fn check(kept: &Kept, scene_hash: &str, setup: &Setup, sampling: Sampling) -> Result<()> {
    if kept.scene_hash != scene_hash {
        bail!("the render refined was of another scene, or of another version of this one");
    }
    if kept.setup != *setup {
        bail!(
            "the render refined had other settings: give the options it was rendered with (size, seed, sampler, \
             bounces, environment, frame...), changing only --spp and --target-error"
        );
    }
    let (old, new) = (kept.sampling, sampling);
    if new.spp < old.spp {
        bail!("the render has {} spp: refining adds samples (--spp {} or more)", old.spp, old.spp);
    }
    if new.spp != old.spp && old.spp % PASS_SPP != 0 {
        bail!(
            "the render's {} spp end in a part of a {PASS_SPP}-spp pass, which cannot be extended bit for bit: render it again",
            old.spp
        );
    }
    match (old.adaptive, new.adaptive) {
        (None, Some(_)) => bail!("the render has a fixed sample count: refine it with more --spp, not a target error"),
        (Some(a), None) => bail!(
            "the render stopped at target error {}: refine it with a --target-error at most that (and --min-spp {})",
            a.target_error,
            a.min_spp
        ),
        (Some(a), Some(b)) if b.target_error > a.target_error => {
            bail!("the render's target error is {}: refining lowers it (at most that)", a.target_error)
        }
        (Some(a), Some(b)) if b.min_spp != a.min_spp => bail!(
            "the render's first round was {} spp and this one's is {}: give --min-spp {} (its default follows --spp)",
            a.min_spp,
            b.min_spp,
            a.min_spp
        ),
        _ => {}
    }
    if old == new {
        bail!("the render already has that quality: nothing to refine (lower --target-error or raise --spp)");
    }
    Ok(())
}
