//! The request's one conversion to and from the protocol (`tessera.v1`), and the bytes the
//! coordinator's store keeps a setup in (the protobuf encoding of its `RenderSettings`, which
//! every database written so far holds). Whatever arrives over the wire is checked here, once,
//! against [`crate::limits`]: the coordinator and the worker both take a request through these
//! functions and nowhere else.

use crate::limits::{
    MAX_BOUNCES, MAX_NAME_BYTES, MAX_PASS_SPP, MAX_SIDE, MAX_SPP, MAX_TILE_SIZE, check_confidence, check_fps,
    check_name, check_priority, check_target_error, check_time,
};
use crate::placement::Placement;
use crate::{Adaptive, EnvironmentMap, Frames, Pose, PreviewFirst, Setup, Submission};
use prost::Message;
use tessera_proto::v1;
use tessera_render::glam::Vec3;
use tessera_render::plan::FrameList;
use tessera_render::{ColorMode, Density, Estimator, LightSampler, RenderSettings, SamplerKind, Termination, Tile};
use tessera_scene::animation::Choice;

/// The settings on the wire (the setup's other fields left empty).
fn settings_to_wire(s: &RenderSettings, environment: Vec3) -> v1::RenderSettings {
    v1::RenderSettings {
        width: s.width,
        height: s.height,
        seed: s.seed,
        estimator: match s.estimator {
            Estimator::Collision => v1::Estimator::Collision,
            Estimator::Nee => v1::Estimator::Nee,
            Estimator::Mis => v1::Estimator::Mis,
        } as i32,
        density: match s.density {
            Density::Uniform => v1::Density::Uniform,
            Density::Cosine => v1::Density::Cosine,
            Density::Brdf => v1::Density::Brdf,
        } as i32,
        sampler: match s.sampler {
            SamplerKind::Independent => v1::Sampler::Independent,
            SamplerKind::Sobol => v1::Sampler::Sobol,
        } as i32,
        termination: Some(match s.termination {
            Termination::MaxBounces(b) => v1::render_settings::Termination::MaxBounces(b),
            // The default keeps its original encoding, so older settings and their hashes stay valid.
            Termination::ROULETTE => v1::render_settings::Termination::RussianRoulette(true),
            Termination::RussianRoulette { from, max_bounces } => {
                v1::render_settings::Termination::Roulette(v1::Roulette { from_bounce: from, max_bounces })
            }
        }),
        camera: s.camera as u32,
        environment_r: environment.x,
        environment_g: environment.y,
        environment_b: environment.z,
        color: match s.color {
            ColorMode::Rgb => v1::ColorMode::Rgb,
            ColorMode::Spectral => v1::ColorMode::Spectral,
        } as i32,
        pose: None,
        environment_map: None,
        transparent: s.transparent,
        variant: String::new(),
        lights: match s.lights {
            LightSampler::Power => v1::LightSampler::Power,
            LightSampler::Tree => v1::LightSampler::Tree,
        } as i32,
        energy_compensation: s.energy_compensation,
        features: s.features,
        denoise: s.denoise,
        confidence: s.confidence,
    }
}

/// Settings from the wire, checked; with the constant environment's radiance.
fn settings_from_wire(w: &v1::RenderSettings) -> Result<(RenderSettings, Vec3), String> {
    if w.width == 0 || w.height == 0 || w.width > MAX_SIDE || w.height > MAX_SIDE {
        return Err(format!("{}x{} is outside 1..={MAX_SIDE} per side", w.width, w.height));
    }
    if w.denoise && !w.features {
        return Err("denoising needs the albedo and normal layers: features must be on with denoise".into());
    }
    check_confidence(w.confidence)?;
    let estimator = match v1::Estimator::try_from(w.estimator) {
        Ok(v1::Estimator::Collision) => Estimator::Collision,
        Ok(v1::Estimator::Nee) => Estimator::Nee,
        Ok(v1::Estimator::Mis) => Estimator::Mis,
        _ => return Err(format!("unknown estimator {}", w.estimator)),
    };
    let density = match v1::Density::try_from(w.density) {
        Ok(v1::Density::Uniform) => Density::Uniform,
        Ok(v1::Density::Cosine) => Density::Cosine,
        Ok(v1::Density::Brdf) => Density::Brdf,
        _ => return Err(format!("unknown density {}", w.density)),
    };
    let sampler = match v1::Sampler::try_from(w.sampler) {
        Ok(v1::Sampler::Independent) => SamplerKind::Independent,
        Ok(v1::Sampler::Sobol) => SamplerKind::Sobol,
        _ => return Err(format!("unknown sampler {}", w.sampler)),
    };
    let termination = match w.termination {
        Some(v1::render_settings::Termination::MaxBounces(b)) if b <= MAX_BOUNCES => Termination::MaxBounces(b),
        Some(v1::render_settings::Termination::MaxBounces(b)) => {
            return Err(format!("max_bounces {b} is over the limit of {MAX_BOUNCES}"));
        }
        Some(v1::render_settings::Termination::RussianRoulette(true)) => Termination::ROULETTE,
        Some(v1::render_settings::Termination::Roulette(r))
            if r.max_bounces <= MAX_BOUNCES && (1..=r.max_bounces).contains(&r.from_bounce) =>
        {
            Termination::RussianRoulette { from: r.from_bounce, max_bounces: r.max_bounces }
        }
        Some(v1::render_settings::Termination::Roulette(r)) => {
            return Err(format!(
                "roulette from bounce {} with at most {} bounces: need 1 <= from <= max <= {MAX_BOUNCES}",
                r.from_bounce, r.max_bounces
            ));
        }
        _ => return Err("no path termination given".into()),
    };
    let color = match v1::ColorMode::try_from(w.color) {
        Ok(v1::ColorMode::Rgb) => ColorMode::Rgb,
        Ok(v1::ColorMode::Spectral) => ColorMode::Spectral,
        _ => return Err(format!("unknown colour mode {}", w.color)),
    };
    let lights = match v1::LightSampler::try_from(w.lights) {
        Ok(v1::LightSampler::Power) => LightSampler::Power,
        Ok(v1::LightSampler::Tree) => LightSampler::Tree,
        _ => return Err(format!("unknown light sampler {}", w.lights)),
    };
    let environment = Vec3::new(w.environment_r, w.environment_g, w.environment_b);
    if !environment.is_finite() || environment.min_element() < 0.0 {
        return Err(format!("environment {environment} must be finite and not negative"));
    }
    let settings = RenderSettings {
        seed: w.seed,
        estimator,
        density,
        sampler,
        termination,
        camera: w.camera as usize,
        color,
        transparent: w.transparent,
        lights,
        energy_compensation: w.energy_compensation,
        features: w.features,
        denoise: w.denoise,
        confidence: w.confidence,
        ..RenderSettings::new(w.width, w.height)
    };
    Ok((settings, environment))
}

impl Pose {
    fn to_wire(&self) -> v1::Pose {
        v1::Pose {
            animation: self.animation.to_wire(),
            time: self.time,
            frame: self.frame,
            fps: self.fps,
            sequence_seed: self.sequence_seed,
        }
    }

    /// A pose from the wire: a finite time, a sane frame rate for a frame, an animation choice.
    /// Whether the animation exists is for whoever loads the scene to say.
    fn from_wire(p: &v1::Pose) -> Result<Self, String> {
        check_time(p.time as f64).map_err(|e| format!("pose time: {e}"))?;
        if p.frame.is_some() {
            check_fps(p.fps).map_err(|e| format!("frame rate: {e}"))?;
        }
        Ok(Pose {
            animation: Choice::from_wire(&p.animation)?,
            time: p.time,
            frame: p.frame,
            fps: p.fps,
            sequence_seed: p.sequence_seed,
        })
    }
}

impl EnvironmentMap {
    fn from_wire(m: &v1::EnvironmentMap) -> Result<Self, String> {
        if !(m.strength.is_finite() && m.strength >= 0.0 && m.rotate_degrees.is_finite()) {
            return Err(format!(
                "environment map strength {} or rotation {} is not a finite number (strength >= 0)",
                m.strength, m.rotate_degrees
            ));
        }
        check_name("the environment map's name", &m.name)?;
        if m.hash.len() > 128 {
            return Err("an environment map's hash is too long".into());
        }
        Ok(EnvironmentMap {
            name: m.name.clone(),
            hash: m.hash.clone(),
            strength: m.strength,
            rotate_degrees: m.rotate_degrees,
        })
    }
}

impl Setup {
    /// The setup as the protocol's `RenderSettings`.
    pub fn to_wire(&self) -> v1::RenderSettings {
        let mut w = settings_to_wire(&self.settings, self.environment);
        w.pose = self.pose.as_ref().map(Pose::to_wire);
        w.environment_map = self.environment_map.as_ref().map(|m| v1::EnvironmentMap {
            name: m.name.clone(),
            hash: m.hash.clone(),
            strength: m.strength,
            rotate_degrees: m.rotate_degrees,
        });
        w.variant = self.variant.clone().unwrap_or_default();
        w
    }

    /// A setup from the wire, every field checked.
    pub fn from_wire(w: &v1::RenderSettings) -> Result<Self, String> {
        let (settings, environment) = settings_from_wire(w)?;
        if w.variant.len() > MAX_NAME_BYTES || w.variant.chars().any(char::is_control) {
            return Err(format!(
                "a material variant's name is over {MAX_NAME_BYTES} bytes or holds control characters"
            ));
        }
        Ok(Setup {
            settings,
            environment,
            pose: w.pose.as_ref().map(Pose::from_wire).transpose()?,
            environment_map: w.environment_map.as_ref().map(EnvironmentMap::from_wire).transpose()?,
            variant: (!w.variant.is_empty()).then(|| w.variant.clone()),
        })
    }

    /// The bytes the coordinator's store keeps a setup in.
    pub fn encode(&self) -> Vec<u8> {
        self.to_wire().encode_to_vec()
    }

    /// A setup from the bytes the store keeps, checked as one from the wire.
    pub fn decode(bytes: &[u8]) -> Result<Self, String> {
        Setup::from_wire(&v1::RenderSettings::decode(bytes).map_err(|e| e.to_string())?)
    }
}

impl Submission {
    /// The submission as the protocol's request.
    pub fn to_wire(&self, protocol_version: u32) -> v1::SubmitRenderRequest {
        v1::SubmitRenderRequest {
            protocol_version,
            scene_hash: self.scene_hash.clone(),
            scene_name: self.scene_name.clone(),
            settings: Some(self.setup.to_wire()),
            spp: self.spp,
            tile_size: self.tile_size,
            pass_spp: self.pass_spp,
            priority: self.priority,
            target_error: self.adaptive.map_or(0.0, |a| a.target_error),
            min_spp: self.adaptive.map_or(0, |a| a.min_spp),
            frames: self.frames.as_ref().map(|f| f.list.to_string()).unwrap_or_default(),
            fps: self.frames.as_ref().map_or(0.0, |f| f.fps),
            name: self.name.clone(),
            pool: self.placement.pool.clone(),
            requires: self.placement.requirement_texts(),
            notify: self.notify.clone(),
            preview_every: self.preview.map_or(0, |p| p.every),
            preview_spp: self.preview.map_or(0, |p| p.spp),
            preview_target_error: self.preview.map_or(0.0, |p| p.target_error),
            paused: self.paused,
        }
    }

    /// A submission from the wire, every field checked against [`crate::limits`] (the farm's
    /// own, lower limits are the coordinator's to check).
    pub fn from_wire(r: &v1::SubmitRenderRequest) -> Result<Self, String> {
        check_name("the scene name", &r.scene_name)?;
        check_name("the render's name", &r.name)?;
        let setup = Setup::from_wire(r.settings.as_ref().ok_or("no render settings")?)?;
        if !(1..=MAX_SPP).contains(&r.spp) {
            return Err(format!("spp {} is outside 1..={MAX_SPP}", r.spp));
        }
        check_target_error(r.target_error)?;
        check_priority(r.priority)?;
        let adaptive =
            (r.target_error > 0.0).then(|| Adaptive { target_error: r.target_error, min_spp: r.min_spp.max(1) });
        if let Some(a) = adaptive
            && a.min_spp > r.spp
        {
            return Err(format!("min spp {} is above spp {}", a.min_spp, r.spp));
        }
        if !(1..=MAX_TILE_SIZE).contains(&r.tile_size) || !(1..=MAX_PASS_SPP).contains(&r.pass_spp) {
            return Err(format!(
                "tile size {} (1..={MAX_TILE_SIZE}) or pass spp {} (1..={MAX_PASS_SPP}) out of range",
                r.tile_size, r.pass_spp
            ));
        }
        crate::limits::check_result_bytes(r.tile_size, setup.settings.features)?;
        let frames = if r.frames.is_empty() {
            None
        } else {
            let list = FrameList::parse(&r.frames).map_err(|e| format!("frames: {e}"))?;
            check_fps(r.fps)?;
            Some(Frames { list, fps: r.fps })
        };
        Ok(Submission {
            scene_hash: r.scene_hash.clone(),
            scene_name: r.scene_name.clone(),
            setup,
            spp: r.spp,
            adaptive,
            tile_size: r.tile_size,
            pass_spp: r.pass_spp,
            priority: r.priority,
            frames,
            name: r.name.clone(),
            placement: Placement::parse(&r.pool, &r.requires)?,
            notify: r.notify.clone(),
            paused: r.paused,
            preview: match (r.preview_every, r.preview_spp, r.preview_target_error) {
                (0, 0, 0.0) => None,
                _ if r.frames.is_empty() => return Err("previews first are for sequences (--frames)".into()),
                (every, 0, e) if every >= 1 && e.is_finite() && e > 0.0 => {
                    check_target_error(e).map_err(|m| format!("the previews' {m}"))?;
                    Some(PreviewFirst { every, spp: 0, target_error: e })
                }
                (every, spp, 0.0) if every >= 1 && (1..=r.spp).contains(&spp) => {
                    Some(PreviewFirst { every, spp, target_error: 0.0 })
                }
                (every, spp, e) => {
                    return Err(format!(
                        "previews every {every} frames at {spp} spp or to error {e}: every at least 1, and one of the \
                         preview's spp (1 to the render's {}) or target error",
                        r.spp
                    ));
                }
            },
        })
    }
}

pub fn tile_to_wire(t: Tile) -> v1::Tile {
    v1::Tile { x0: t.x0, y0: t.y0, width: t.width, height: t.height }
}

pub fn tile_from_wire(t: &v1::Tile) -> Tile {
    Tile { x0: t.x0, y0: t.y0, width: t.width, height: t.height }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> RenderSettings {
        RenderSettings {
            seed: 99,
            estimator: Estimator::Nee,
            density: Density::Cosine,
            sampler: SamplerKind::Independent,
            termination: Termination::MaxBounces(5),
            camera: 2,
            color: ColorMode::Spectral,
            transparent: true,
            lights: LightSampler::Tree,
            ..RenderSettings::new(640, 480)
        }
    }

    fn wire() -> v1::RenderSettings {
        settings_to_wire(&settings(), Vec3::ZERO)
    }

    #[test]
    fn settings_round_trip() {
        let env = Vec3::new(0.1, 0.2, 0.3);
        let (s, e) = settings_from_wire(&settings_to_wire(&settings(), env)).unwrap();
        assert_eq!((s, e), (settings(), env));
        let mut rr = settings();
        rr.termination = Termination::ROULETTE;
        let wire = settings_to_wire(&rr, env);
        // `--rr` keeps the encoding it had before roulette took parameters.
        assert_eq!(wire.termination, Some(v1::render_settings::Termination::RussianRoulette(true)));
        assert_eq!(settings_from_wire(&wire).unwrap().0, rr);
        rr.termination = Termination::RussianRoulette { from: 5, max_bounces: 7 };
        assert_eq!(settings_from_wire(&settings_to_wire(&rr, env)).unwrap().0, rr);
        // Energy compensation travels both ways; a request from before it (the field absent,
        // read as false) renders without it, as it did then.
        for on in [true, false] {
            let s = RenderSettings { energy_compensation: on, ..settings() };
            assert_eq!(settings_from_wire(&settings_to_wire(&s, env)).unwrap().0.energy_compensation, on);
        }
        let old = v1::RenderSettings { energy_compensation: Default::default(), ..settings_to_wire(&settings(), env) };
        assert!(!settings_from_wire(&old).unwrap().0.energy_compensation);
        // So do the feature layers; off when absent.
        let layered = RenderSettings { features: true, ..settings() };
        assert_eq!(settings_from_wire(&settings_to_wire(&layered, env)).unwrap().0, layered);
        assert!(!settings_from_wire(&settings_to_wire(&settings(), env)).unwrap().0.features);
        let denoised = RenderSettings { features: true, denoise: true, ..settings() };
        assert_eq!(settings_from_wire(&settings_to_wire(&denoised, env)).unwrap().0, denoised);
        let stated = RenderSettings { confidence: 0.95, ..settings() };
        assert_eq!(settings_from_wire(&settings_to_wire(&stated, env)).unwrap().0, stated);
    }

    #[test]
    fn absurd_settings_are_refused() {
        let refused = |change: &dyn Fn(&mut v1::RenderSettings)| {
            let mut w = wire();
            change(&mut w);
            Setup::from_wire(&w).unwrap_err()
        };
        assert!(refused(&|w| w.width = 0).contains("0x480"));
        assert!(refused(&|w| w.estimator = 42).contains("estimator"));
        assert!(refused(&|w| w.lights = 7).contains("unknown light sampler 7"));
        assert!(refused(&|w| w.termination = None).contains("no path termination"));
        for (from_bounce, max_bounces) in [(0, 7), (8, 7), (1, MAX_BOUNCES + 1)] {
            let e = refused(&|w| {
                w.termination =
                    Some(v1::render_settings::Termination::Roulette(v1::Roulette { from_bounce, max_bounces }))
            });
            assert!(e.contains(&format!("roulette from bounce {from_bounce} with at most {max_bounces}")), "{e}");
        }
        assert!(refused(&|w| w.environment_g = f32::NAN).contains("environment"));
        assert!(refused(&|w| w.color = 7).contains("colour mode 7"));
        assert!(refused(&|w| w.denoise = true).contains("features must be on"));
        assert!(refused(&|w| w.confidence = 0.3).contains("confidence 0.3"));
        assert!(refused(&|w| w.confidence = f32::NAN).contains("confidence"));
        for variant in ["v".repeat(1025), "evil\x1b[2J".to_string()] {
            assert!(refused(&|w| w.variant = variant.clone()).contains("material variant"));
        }
        assert!(refused(&|w| w.pose = Some(v1::Pose { time: f32::NAN, ..Default::default() })).contains("pose time"));
        assert!(
            refused(&|w| w.pose = Some(v1::Pose { animation: "?".into(), ..Default::default() }))
                .contains("not an animation choice")
        );
        let map = |strength| v1::EnvironmentMap { strength, ..Default::default() };
        assert!(refused(&|w| w.environment_map = Some(map(f32::INFINITY))).contains("strength"));
        let mut w = wire();
        w.variant = "v".repeat(1024);
        assert!(Setup::from_wire(&w).is_ok(), "a 1024-byte variant name is within the bound");
    }

    fn setup() -> Setup {
        Setup {
            settings: RenderSettings {
                seed: 99,
                termination: Termination::MaxBounces(6),
                camera: 2,
                ..RenderSettings::new(31, 17)
            },
            environment: Vec3::new(0.25, 0.5, 2.0),
            pose: Some(Pose {
                animation: Choice::Name("walk".into()),
                time: 1.25,
                frame: Some(30),
                fps: 24.0,
                sequence_seed: 7,
            }),
            environment_map: Some(EnvironmentMap {
                name: "sky.hdr".into(),
                hash: "ab".repeat(32),
                strength: 1.5,
                rotate_degrees: -90.0,
            }),
            variant: Some("midnight".into()),
        }
    }

    #[test]
    fn a_setup_keeps_every_field_through_the_stored_encoding() {
        assert_eq!(Setup::decode(&setup().encode()).unwrap(), setup());
        assert!(Setup::decode(b"\xff\xff").is_err(), "bytes that are no setup are refused");
    }

    fn submission() -> Submission {
        Submission {
            scene_hash: "ab".repeat(32),
            scene_name: "walk.glb".into(),
            setup: setup(),
            spp: 256,
            adaptive: Some(Adaptive { target_error: 0.01, min_spp: 32 }),
            tile_size: 32,
            pass_spp: 16,
            priority: 3,
            frames: Some(Frames { list: FrameList::parse("1-48x2").unwrap(), fps: 24.0 }),
            name: "shot 12, take 3".into(),
            placement: Placement::parse("gpu", &["mem>=32G".into(), "avx512f".into(), "site=paris".into()]).unwrap(),
            notify: "https://hooks.example.com/tessera".into(),
            preview: Some(PreviewFirst { every: 8, spp: 16, target_error: 0.0 }),
            paused: true,
        }
    }

    #[test]
    fn a_submission_keeps_every_field_through_the_wire() {
        assert_eq!(Submission::from_wire(&submission().to_wire(4)).unwrap(), submission());
        let still = Submission { adaptive: None, frames: None, preview: None, ..submission() };
        assert_eq!(Submission::from_wire(&still.to_wire(4)).unwrap(), still);
        let targeted = PreviewFirst { every: 4, spp: 0, target_error: 0.05 };
        let targeted = Submission { preview: Some(targeted), ..submission() };
        assert_eq!(Submission::from_wire(&targeted.to_wire(4)).unwrap(), targeted);
    }

    #[test]
    fn absurd_submissions_are_refused_naming_the_field() {
        let refused = |change: &dyn Fn(&mut v1::SubmitRenderRequest)| {
            let mut w = submission().to_wire(4);
            change(&mut w);
            Submission::from_wire(&w).unwrap_err()
        };
        assert!(refused(&|w| w.spp = 0).contains("spp 0"));
        assert!(refused(&|w| w.spp = MAX_SPP + 1).contains("outside"));
        assert!(refused(&|w| w.target_error = f32::NAN).contains("target error"));
        assert!(refused(&|w| w.min_spp = 1 << 19).contains("min spp"));
        assert!(refused(&|w| w.tile_size = 0).contains("tile size"));
        // The largest tiles whose every result fits what a coordinator accepts, with and
        // without the feature layers; one pixel more a side is refused, saying what fits.
        assert!(Submission::from_wire(&Submission { tile_size: 940, ..submission() }.to_wire(1)).is_ok());
        let e = refused(&|w| w.tile_size = 941);
        assert!(e.contains("941 x 941") && e.contains("at most 940 pixels a side"), "{e}");
        let mut layered = submission();
        layered.setup.settings.features = true;
        assert!(Submission::from_wire(&Submission { tile_size: 798, ..layered.clone() }.to_wire(1)).is_ok());
        let e = Submission::from_wire(&Submission { tile_size: 799, ..layered }.to_wire(1)).unwrap_err();
        assert!(e.contains("with the albedo and normal layers") && e.contains("at most 798"), "{e}");
        assert!(refused(&|w| w.pass_spp = MAX_PASS_SPP + 1).contains("pass spp"));
        assert!(refused(&|w| w.frames = "3-1".into()).contains("runs backwards"));
        assert!(refused(&|w| w.frames = "1-100001".into()).contains("more than 100000"));
        assert!(refused(&|w| w.fps = 0.0).contains("fps 0"));
        assert!(refused(&|w| w.fps = f64::NAN).contains("fps NaN"));
        assert!(refused(&|w| w.scene_name = "x".repeat(4 << 20)).contains("over the 1024-byte limit"));
        assert!(refused(&|w| w.scene_name = "evil\x1b[2J".into()).contains("control or invisible format characters"));
        assert!(refused(&|w| w.scene_name = "evil\u{202e}gnp".into()).contains("format characters"));
        assert!(refused(&|w| w.name = "evil\x1b[2J".into()).contains("control or invisible format characters"));
        assert!(refused(&|w| w.settings = None).contains("no render settings"));
        assert!(refused(&|w| w.preview_every = 0).contains("every at least 1"));
        assert!(refused(&|w| w.preview_target_error = 0.05).contains("one of the preview's spp"));
        assert!(refused(&|w| (w.preview_spp, w.preview_target_error) = (0, f32::NAN)).contains("every at least 1"));
        assert!(refused(&|w| w.preview_spp = w.spp + 1).contains("1 to the render's"));
        assert!(refused(&|w| w.frames.clear()).contains("for sequences"));
        assert!(refused(&|w| w.priority = 1001).contains("-1000..=1000"));
        assert!(refused(&|w| w.pool = "a b".into()).contains("the pool"));
        assert!(refused(&|w| w.requires = vec!["mem>=lots".into()]).contains("not an amount"));
    }
}
