//! The limits of a request, defined once: the command line's flags (clap), the coordinator's
//! wire checks and its configuration defaults, and the worker's all read them from here.

use tessera_render::ROULETTE_MAX_BOUNCES;

/// Largest image side, in pixels.
pub const MAX_SIDE: u32 = 16384;
/// Largest image area: a film holds 112 bytes of exact sums per pixel (1.9 GB here).
pub const MAX_PIXELS: u64 = 1 << 24;
/// Most samples per pixel.
pub const MAX_SPP: u32 = 1 << 20;
/// Longest path, in bounces.
pub const MAX_BOUNCES: u32 = ROULETTE_MAX_BOUNCES;
/// Largest tile side, in pixels.
pub const MAX_TILE_SIZE: u32 = 1024;
/// Most samples in one pass.
pub const MAX_PASS_SPP: u32 = 1 << 16;
/// Most frames in one sequence, and the last frame number.
pub use tessera_render::plan::{MAX_FRAME, MAX_FRAMES};
/// Highest frame rate, in frames per second.
pub const MAX_FPS: f64 = 1e6;
/// Largest time in an animation, in seconds either way.
pub const MAX_TIME: f64 = 1e9;
/// Largest relative error adaptive sampling may aim for (0 turns it off).
pub const MAX_TARGET_ERROR: f32 = 10.0;
/// Longest name (a scene, a worker, a material variant, an animation, a map), in bytes.
pub const MAX_NAME_BYTES: usize = 1024;

/// Refuses a name that is too long or carries control characters (which would print as
/// terminal escape sequences in `tessera status` and the logs).
pub fn check_name(what: &str, name: &str) -> Result<(), String> {
    if name.len() > MAX_NAME_BYTES {
        return Err(format!("{what} is {} bytes, over the {MAX_NAME_BYTES}-byte limit", name.len()));
    }
    if name.chars().any(char::is_control) {
        return Err(format!("{what} '{}' holds control characters", name.escape_debug()));
    }
    Ok(())
}

/// Refuses a frame rate that is not a positive number up to [`MAX_FPS`].
pub fn check_fps(fps: f64) -> Result<(), String> {
    if fps.is_finite() && fps > 0.0 && fps <= MAX_FPS {
        Ok(())
    } else {
        Err(format!("fps {fps} is not a positive number of frames per second (at most {MAX_FPS})"))
    }
}

/// Refuses a time that is not a finite number of seconds up to [`MAX_TIME`] either way.
pub fn check_time(seconds: f64) -> Result<(), String> {
    if seconds.is_finite() && seconds.abs() <= MAX_TIME {
        Ok(())
    } else {
        Err(format!("{seconds} s is not a time in seconds (at most {MAX_TIME} either way)"))
    }
}

/// Refuses a target error outside `0..MAX_TARGET_ERROR` (0 turns adaptive sampling off).
pub fn check_target_error(e: f32) -> Result<(), String> {
    if e.is_finite() && (0.0..MAX_TARGET_ERROR).contains(&e) {
        Ok(())
    } else {
        Err(format!(
            "target error {e} is not a relative error between 0 and {MAX_TARGET_ERROR} (0 turns adaptive sampling off)"
        ))
    }
}
