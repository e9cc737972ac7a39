//! Render settings between the wire and the renderer, validated on the way in.

use crate::WireError;
use crate::v1;
use tessera_render::glam::Vec3;
use tessera_render::{ColorMode, Density, Estimator, LightSampler, RenderSettings, SamplerKind, Termination, Tile};

pub fn settings_to_wire(s: &RenderSettings, environment: Vec3) -> v1::RenderSettings {
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
    }
}

/// Largest image side and path length accepted from the wire.
pub const MAX_SIDE: u32 = 16384;
pub const MAX_BOUNCES: u32 = tessera_render::ROULETTE_MAX_BOUNCES;

/// Converts and validates wire settings; returns the settings and the environment radiance.
pub fn settings_from_wire(w: &v1::RenderSettings) -> Result<(RenderSettings, Vec3), WireError> {
    let bad = |m: String| WireError::Settings(m);
    if w.width == 0 || w.height == 0 || w.width > MAX_SIDE || w.height > MAX_SIDE {
        return Err(bad(format!("{}x{} is outside 1..={MAX_SIDE} per side", w.width, w.height)));
    }
    let estimator = match v1::Estimator::try_from(w.estimator) {
        Ok(v1::Estimator::Collision) => Estimator::Collision,
        Ok(v1::Estimator::Nee) => Estimator::Nee,
        Ok(v1::Estimator::Mis) => Estimator::Mis,
        _ => return Err(bad(format!("unknown estimator {}", w.estimator))),
    };
    let density = match v1::Density::try_from(w.density) {
        Ok(v1::Density::Uniform) => Density::Uniform,
        Ok(v1::Density::Cosine) => Density::Cosine,
        Ok(v1::Density::Brdf) => Density::Brdf,
        _ => return Err(bad(format!("unknown density {}", w.density))),
    };
    let sampler = match v1::Sampler::try_from(w.sampler) {
        Ok(v1::Sampler::Independent) => SamplerKind::Independent,
        Ok(v1::Sampler::Sobol) => SamplerKind::Sobol,
        _ => return Err(bad(format!("unknown sampler {}", w.sampler))),
    };
    let termination = match w.termination {
        Some(v1::render_settings::Termination::MaxBounces(b)) if b <= MAX_BOUNCES => Termination::MaxBounces(b),
        Some(v1::render_settings::Termination::MaxBounces(b)) => {
            return Err(bad(format!("max_bounces {b} is over the limit of {MAX_BOUNCES}")));
        }
        Some(v1::render_settings::Termination::RussianRoulette(true)) => Termination::ROULETTE,
        Some(v1::render_settings::Termination::Roulette(r))
            if r.max_bounces <= MAX_BOUNCES && (1..=r.max_bounces).contains(&r.from_bounce) =>
        {
            Termination::RussianRoulette { from: r.from_bounce, max_bounces: r.max_bounces }
        }
        Some(v1::render_settings::Termination::Roulette(r)) => {
            return Err(bad(format!(
                "roulette from bounce {} with at most {} bounces: need 1 <= from <= max <= {MAX_BOUNCES}",
                r.from_bounce, r.max_bounces
            )));
        }
        _ => return Err(bad("no path termination given".into())),
    };
    let color = match v1::ColorMode::try_from(w.color) {
        Ok(v1::ColorMode::Rgb) => ColorMode::Rgb,
        Ok(v1::ColorMode::Spectral) => ColorMode::Spectral,
        _ => return Err(bad(format!("unknown colour mode {}", w.color))),
    };
    let lights = match v1::LightSampler::try_from(w.lights) {
        Ok(v1::LightSampler::Power) => LightSampler::Power,
        Ok(v1::LightSampler::Tree) => LightSampler::Tree,
        _ => return Err(bad(format!("unknown light sampler {}", w.lights))),
    };
    let environment = Vec3::new(w.environment_r, w.environment_g, w.environment_b);
    if !environment.is_finite() || environment.min_element() < 0.0 {
        return Err(bad(format!("environment {environment} must be finite and not negative")));
    }
    if let Some(p) = &w.pose {
        check_pose(p).map_err(bad)?;
    }
    if w.variant.len() > 1024 || w.variant.chars().any(char::is_control) {
        return Err(bad("a material variant's name is over 1024 bytes or holds control characters".into()));
    }
    if let Some(m) = &w.environment_map {
        if !(m.strength.is_finite() && m.strength >= 0.0 && m.rotate_degrees.is_finite()) {
            return Err(bad(format!(
                "environment map strength {} or rotation {} is not a finite number (strength >= 0)",
                m.strength, m.rotate_degrees
            )));
        }
        if m.name.len() > 1024 || m.hash.len() > 128 {
            return Err(bad("an environment map's name or hash is too long".into()));
        }
    }
    let settings = RenderSettings {
        width: w.width,
        height: w.height,
        seed: w.seed,
        estimator,
        density,
        sampler,
        termination,
        camera: w.camera as usize,
        color,
        transparent: w.transparent,
        lights,
    };
    Ok((settings, environment))
}

/// The numbers of a pose that arrive over the wire: a finite time, a sane frame rate, a name of
/// bounded length. Whether the animation exists is for whoever loads the scene to say.
pub fn check_pose(p: &v1::Pose) -> Result<(), String> {
    if !p.time.is_finite() || p.time.abs() > 1e9 {
        return Err(format!("pose time {} s is not a finite time", p.time));
    }
    if p.animation.len() > 1024 {
        return Err(format!("an animation name of {} bytes", p.animation.len()));
    }
    if p.frame.is_some() && !(p.fps.is_finite() && p.fps > 0.0 && p.fps <= 1e6) {
        return Err(format!("frame rate {} is not a positive number of frames per second", p.fps));
    }
    Ok(())
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
            width: 640,
            height: 480,
            seed: 99,
            estimator: Estimator::Nee,
            density: Density::Cosine,
            sampler: SamplerKind::Independent,
            termination: Termination::MaxBounces(5),
            camera: 2,
            color: ColorMode::Spectral,
            transparent: true,
            lights: LightSampler::Tree,
        }
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
    }

    #[test]
    fn absurd_settings_are_refused() {
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.width = 0;
        assert!(settings_from_wire(&w).unwrap_err().to_string().contains("0x480"));
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.estimator = 42;
        assert!(settings_from_wire(&w).unwrap_err().to_string().contains("estimator"));
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.lights = 7;
        assert!(settings_from_wire(&w).unwrap_err().to_string().contains("unknown light sampler 7"));
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.termination = None;
        assert!(settings_from_wire(&w).is_err());
        for (from_bounce, max_bounces) in [(0, 7), (8, 7), (1, MAX_BOUNCES + 1)] {
            let mut w = settings_to_wire(&settings(), Vec3::ZERO);
            w.termination = Some(v1::render_settings::Termination::Roulette(v1::Roulette { from_bounce, max_bounces }));
            let e = settings_from_wire(&w).unwrap_err().to_string();
            assert!(e.contains(&format!("roulette from bounce {from_bounce} with at most {max_bounces}")), "{e}");
        }
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.environment_g = f32::NAN;
        assert!(settings_from_wire(&w).is_err());
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.color = 7;
        assert!(settings_from_wire(&w).unwrap_err().to_string().contains("colour mode 7"));
        for variant in ["v".repeat(1025), "evil\x1b[2J".to_string()] {
            let mut w = settings_to_wire(&settings(), Vec3::ZERO);
            w.variant = variant;
            assert!(settings_from_wire(&w).unwrap_err().to_string().contains("material variant"));
        }
        let mut w = settings_to_wire(&settings(), Vec3::ZERO);
        w.variant = "v".repeat(1024);
        assert!(settings_from_wire(&w).is_ok(), "a 1024-byte variant name is within the bound");
    }
}
