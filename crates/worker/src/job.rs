//! The worker's synchronous core: a job's numbers checked and turned into what to render
//! ([`JobPlan`]), the scenes kept between jobs ([`SceneCache`]: files read once, scenes posed once
//! per (hash, environment, animation, time)), and a job's samples split over threads with exact
//! sums ([`render_split`]). No sockets, no async: `lib.rs` is the shell that leases, fetches and
//! reports.

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::Arc;
use tessera_proto::v1::Job;
use tessera_render::plan::pass_samples;
use tessera_render::{RenderSettings, Scene, Tile, TileSums, render_tile};
use tessera_request::Setup;
use tessera_request::wire::tile_from_wire;
use tessera_scene::{LoadOptions, Source};

/// What a job asks for, checked: every number came over the wire.
#[derive(Clone, Debug)]
pub struct JobPlan {
    pub scene_hash: String,
    pub setup: Setup,
    pub tile: Tile,
    pub samples: Range<u32>,
}

impl JobPlan {
    /// Checks a job: its setup as every request from the wire is checked (`Setup::from_wire`),
    /// a tile inside the image and within the wire's size limit, passes of at least one sample,
    /// no arithmetic that wraps.
    pub fn from_job(job: &Job) -> Result<JobPlan, String> {
        let setup = Setup::from_wire(job.settings.as_ref().ok_or("job without settings")?)?;
        let settings = &setup.settings;
        let tile = tile_from_wire(job.tile.as_ref().ok_or("job without tile")?);
        let inside = tile.x0.checked_add(tile.width).is_some_and(|x| x <= settings.width)
            && tile.y0.checked_add(tile.height).is_some_and(|y| y <= settings.height);
        let pixels = tile.width as u64 * tile.height as u64;
        if !inside || pixels == 0 || pixels > tessera_proto::sums::MAX_TILE_PIXELS || job.pass_spp == 0 {
            return Err(format!(
                "job {} is malformed: tile {tile:?} of a {}x{} image, {} samples per pass",
                job.lease_id, settings.width, settings.height, job.pass_spp
            ));
        }
        Ok(JobPlan {
            scene_hash: job.scene_hash.clone(),
            samples: pass_samples(job.first_pass, job.pass_count, job.pass_spp, job.spp),
            setup,
            tile,
        })
    }

    /// What a posed scene is kept under: the scene, the environment's bits (the map's strength
    /// and rotation), the pose.
    pub fn scene_key(&self) -> SceneKey {
        let s = &self.setup;
        let map = s.environment_map.as_ref().map_or([0; 3], |m| [1, m.strength.to_bits(), m.rotate_degrees.to_bits()]);
        (
            self.scene_hash.clone(),
            [s.environment.to_array().map(f32::to_bits), map].concat(),
            s.pose.as_ref().map(|p| (p.animation.to_wire(), p.time.to_bits())),
            s.variant.clone(),
        )
    }

    /// The options that pose the scene file as this job needs it.
    pub fn load_options(&self) -> LoadOptions {
        LoadOptions {
            environment: Some(self.setup.environment),
            pose: self.setup.pose.as_ref().map(|p| p.at()),
            variant: self.setup.variant.clone(),
            ..Default::default()
        }
    }
}

/// A posed scene's key: the scene's hash, the environment's bits, the pose's wire form
/// (animation, time bits), the material variant.
pub type SceneKey = (String, Vec<u32>, Option<(String, u32)>, Option<String>);

/// Scenes kept between jobs, most recently used first: scene files read (a few), and scenes
/// posed from them (`posed_kept`), so that the jobs of one frame pose and build it once.
pub struct SceneCache {
    sources: VecDeque<(String, Arc<Source>)>,
    posed: VecDeque<(SceneKey, Arc<Scene>)>,
    posed_kept: usize,
}

/// Scene files kept read.
pub const SOURCES_KEPT: usize = 2;

impl SceneCache {
    pub fn new(posed_kept: usize) -> Self {
        Self { sources: VecDeque::new(), posed: VecDeque::new(), posed_kept: posed_kept.max(1) }
    }

    /// The posed scene kept under `key`, now the most recently used.
    pub fn posed(&mut self, key: &SceneKey) -> Option<Arc<Scene>> {
        touch(&mut self.posed, key)
    }

    /// The scene file `hash`, if it is kept, now the most recently used.
    pub fn source(&mut self, hash: &str) -> Option<Arc<Source>> {
        touch(&mut self.sources, &hash.to_string())
    }

    pub fn keep_source(&mut self, hash: &str, source: Arc<Source>) {
        keep(&mut self.sources, hash.to_string(), source, SOURCES_KEPT);
    }

    pub fn keep_posed(&mut self, key: SceneKey, scene: Arc<Scene>) {
        keep(&mut self.posed, key, scene, self.posed_kept);
    }
}

/// The value kept under `key` in a most-recently-used-first list, moved to the front.
fn touch<K: PartialEq, V: Clone>(list: &mut VecDeque<(K, V)>, key: &K) -> Option<V> {
    let hit = list.remove(list.iter().position(|(k, _)| k == key)?)?;
    let value = hit.1.clone();
    list.push_front(hit);
    Some(value)
}

/// Puts `value` at the front under `key` (replacing an older one), keeping at most `most`.
fn keep<K: PartialEq, V>(list: &mut VecDeque<(K, V)>, key: K, value: V, most: usize) {
    list.retain(|(k, _)| k != &key);
    list.push_front((key, value));
    list.truncate(most);
}

/// A scene is content-addressed: the bytes that arrived must be what their hash names (a
/// corrupted copy is refused before it is parsed or kept).
pub fn check_scene_bytes(hash: &str, bytes: &[u8]) -> Result<(), String> {
    if blake3::hash(bytes).to_hex().as_str() == hash {
        Ok(())
    } else {
        Err(format!("scene {hash} arrived corrupted: its bytes do not match its hash"))
    }
}

/// Poses `source` as `plan` needs it (the slow part of a new frame: meshes and the BVH).
pub fn pose(source: &Source, plan: &JobPlan) -> Result<Scene, String> {
    let mut options = plan.load_options();
    if let Some(m) = &plan.setup.environment_map {
        let map = source.environment(m.strength, m.rotate_degrees).map_err(|e| e.to_string())?;
        let map = map.ok_or("the job asks for an environment map that its scene package does not carry")?;
        options.environment_map = Some(map.map);
    }
    source.pose(&options).map(|l| l.scene).map_err(|e| e.to_string())
}

/// Renders `samples` of `tile` split over `threads` on `pool`: contiguous sample ranges, one a
/// thread, summed exactly, so the split leaves no trace in the bits.
pub fn render_split(
    pool: &rayon::ThreadPool,
    threads: u32,
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
) -> Result<TileSums, String> {
    use rayon::prelude::*;
    let threads = threads.max(1);
    let per = (samples.len() as u32).div_ceil(threads).max(1);
    let ranges: Vec<Range<u32>> = (0..threads)
        .map(|i| {
            let at = |k: u32| samples.start.saturating_add(k.saturating_mul(per)).min(samples.end);
            at(i)..at(i + 1)
        })
        .filter(|r| !r.is_empty())
        .collect();
    let parts: Result<Vec<TileSums>, _> =
        pool.install(|| ranges.par_iter().map(|r| render_tile(scene, settings, tile, r.clone())).collect());
    let mut total = TileSums::new(tile);
    for p in &parts.map_err(|e| e.to_string())? {
        total.merge(p);
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_proto::v1;
    use tessera_render::glam::Vec3;

    fn settings() -> RenderSettings {
        RenderSettings { termination: tessera_render::Termination::MaxBounces(4), ..RenderSettings::new(64, 32) }
    }

    fn job(tile: (u32, u32, u32, u32), first_pass: u32, pass_count: u32, pass_spp: u32) -> Job {
        let (x0, y0, width, height) = tile;
        Job {
            lease_id: "7".into(),
            scene_hash: "h".into(),
            settings: Some(Setup::new(settings(), Vec3::ONE).to_wire()),
            tile: Some(v1::Tile { x0, y0, width, height }),
            first_pass,
            pass_count,
            pass_spp,
            spp: 64,
            ..Default::default()
        }
    }

    /// A job's numbers come over the wire: a tile outside the image, an empty tile and passes of
    /// no samples are refused; pass arithmetic that would wrap a u32 is clamped instead.
    #[test]
    fn malformed_jobs_are_refused_and_pass_arithmetic_cannot_wrap() {
        let samples =
            |tile, first, count, pass_spp| JobPlan::from_job(&job(tile, first, count, pass_spp)).map(|p| p.samples);
        assert_eq!(samples((0, 0, 32, 32), 1, 2, 16).unwrap(), 16..48);
        assert_eq!(samples((32, 0, 32, 32), u32::MAX, u32::MAX, 16).unwrap(), 64..64, "clamped, not wrapped");
        for (tile, pass_spp) in [
            ((48, 0, 32, 32), 16),     // past the right edge
            ((1, 0, u32::MAX, 2), 16), // x0 + width wraps
            ((0, 0, 0, 32), 16),       // empty
            ((0, 0, 32, 32), 0),       // passes of no samples
        ] {
            assert!(samples(tile, 0, 1, pass_spp).unwrap_err().contains("malformed"), "{tile:?} {pass_spp}");
        }
        let mut bad = job((0, 0, 32, 32), 0, 1, 16);
        bad.settings.as_mut().unwrap().pose = Some(v1::Pose { animation: "?".into(), ..Default::default() });
        assert!(JobPlan::from_job(&bad).unwrap_err().contains("not an animation choice"));
        bad.settings.as_mut().unwrap().pose = Some(v1::Pose { time: f32::NAN, ..Default::default() });
        assert!(JobPlan::from_job(&bad).unwrap_err().contains("pose time"));
        bad.settings = None;
        assert!(JobPlan::from_job(&bad).is_err());
    }

    #[test]
    fn a_scene_whose_bytes_do_not_match_its_hash_is_refused() {
        let bytes = b"tessera-builtin:cornell-box".to_vec();
        let hash = blake3::hash(&bytes).to_hex().to_string();
        assert!(check_scene_bytes(&hash, &bytes).is_ok());
        let mut flipped = bytes.clone();
        flipped[3] ^= 0x10;
        assert!(check_scene_bytes(&hash, &flipped).unwrap_err().contains("arrived corrupted"));
    }

    #[test]
    fn a_split_over_threads_gives_the_bits_of_one_render() {
        let scene = tessera_scene::load("builtin:cornell-box", &LoadOptions::default()).unwrap().scene;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let tile = Tile { x0: 16, y0: 8, width: 8, height: 8 };
        let s = RenderSettings { width: 64, height: 64, ..settings() };
        let whole = render_tile(&scene, &s, tile, 5..37).unwrap();
        for threads in [1, 2, 3, 7, 40] {
            let split = render_split(&pool, threads, &scene, &s, tile, 5..37).unwrap();
            assert_eq!(split.pixels, whole.pixels, "{threads} threads");
        }
        assert!(render_split(&pool, 3, &scene, &s, tile, 9..9).unwrap().pixels.iter().all(|p| p.n == 0));
    }

    #[test]
    fn scenes_are_posed_once_per_key_and_the_least_recent_go_first() {
        let source = Arc::new(tessera_scene::open("builtin:furnace").unwrap());
        let mut cache = SceneCache::new(2);
        let plan = |time: f32, env: f32| {
            let mut j = job((0, 0, 32, 32), 0, 1, 16);
            let w = j.settings.as_mut().unwrap();
            (w.environment_r, w.pose) = (env, Some(v1::Pose { time, ..Default::default() }));
            JobPlan::from_job(&j).unwrap()
        };
        let (a, b, c) = (plan(0.0, 1.0), plan(0.5, 1.0), plan(0.0, 2.0));
        assert_ne!(a.scene_key(), b.scene_key(), "another time is another scene");
        assert_ne!(a.scene_key(), c.scene_key(), "another environment is another scene");
        assert!(cache.posed(&a.scene_key()).is_none());
        let posed = Arc::new(pose(&source, &a).unwrap());
        cache.keep_posed(a.scene_key(), posed.clone());
        assert!(Arc::ptr_eq(&cache.posed(&a.scene_key()).unwrap(), &posed), "the same scene, not posed again");
        cache.keep_posed(b.scene_key(), Arc::new(pose(&source, &b).unwrap()));
        // a was used last: c pushes b out.
        assert!(cache.posed(&a.scene_key()).is_some());
        cache.keep_posed(c.scene_key(), Arc::new(pose(&source, &c).unwrap()));
        assert!(cache.posed(&b.scene_key()).is_none() && cache.posed(&a.scene_key()).is_some());
        for h in ["x", "y", "z"] {
            cache.keep_source(h, source.clone());
        }
        assert!(cache.source("x").is_none() && cache.source("y").is_some() && cache.source("z").is_some());
    }
}
