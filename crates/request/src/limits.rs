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
/// Largest encoded result (one job's tile sums) a coordinator accepts. A submission's tiles are
/// held to it at their worst case ([`check_result_bytes`]), so that no honest result is refused.
pub const MAX_RESULT_BYTES: usize = 130 << 20;

/// Refuses tiles of `tile_size` pixels a side whose result, at its longest encoding (every
/// pixel's sums at their largest, with the feature layers when `features`), could pass
/// [`MAX_RESULT_BYTES`].
pub fn check_result_bytes(tile_size: u32, features: bool) -> Result<(), String> {
    use tessera_proto::sums::{HEADER_BYTES, MAX_PIXEL_BYTES, MAX_PIXEL_BYTES_WITH_FEATURES};
    let per_pixel = if features { MAX_PIXEL_BYTES_WITH_FEATURES } else { MAX_PIXEL_BYTES };
    // In 128 bits: a stored render's tile size comes here unbounded (a submission's is held to
    // MAX_TILE_SIZE first), and any u32 side squared times a pixel's bytes fits.
    let bytes = |side: u32| side as u128 * side as u128 * per_pixel as u128;
    let fits = |side: u32| bytes(side) + HEADER_BYTES as u128 <= MAX_RESULT_BYTES as u128;
    if fits(tile_size) {
        return Ok(());
    }
    // No side past MAX_TILE_SIZE fits (checked below), so the search is at most that long.
    let largest = (1..=tile_size.min(MAX_TILE_SIZE)).rev().find(|&s| fits(s)).unwrap_or(1);
    let with = if features { " with the albedo and normal layers" } else { "" };
    Err(format!(
        "tiles of {tile_size} x {tile_size} pixels{with} can make results of up to {} MiB, over the {} MiB one result may be: use tiles of at most {largest} pixels a side",
        bytes(tile_size) >> 20,
        MAX_RESULT_BYTES >> 20
    ))
}

const _: () = assert!(
    MAX_TILE_SIZE as usize * MAX_TILE_SIZE as usize * tessera_proto::sums::MAX_PIXEL_BYTES > MAX_RESULT_BYTES,
    "check_result_bytes searches for the largest side that fits below MAX_TILE_SIZE"
);

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

/// Refuses a name that is too long or carries characters a terminal would not show as text:
/// controls (escape sequences in `tessera status` and the logs) and format characters (a bidi
/// override makes `status` show a name other than the one stored).
pub fn check_name(what: &str, name: &str) -> Result<(), String> {
    if name.len() > MAX_NAME_BYTES {
        return Err(format!("{what} is {} bytes, over the {MAX_NAME_BYTES}-byte limit", name.len()));
    }
    if name.chars().any(unprintable) {
        return Err(format!("{what} '{}' holds control or invisible format characters", crate::printable(name)));
    }
    Ok(())
}

/// Longest error message a coordinator sends or logs; one that quotes a request at length (a
/// name from a scene file) is cut there.
pub const MAX_MESSAGE_BYTES: usize = 2048;

/// `text` cut to at most `max` bytes on a character boundary, saying how much was left out.
pub fn clip(text: &str, max: usize) -> std::borrow::Cow<'_, str> {
    if text.len() <= max {
        return text.into();
    }
    let mut end = max;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}... ({} more bytes)", &text[..end], text.len() - end).into()
}

/// Unicode's format characters (general category Cf: bidi embeddings, overrides and isolates,
/// zero-width spaces and joiners, the byte-order mark, tags) and the line and paragraph
/// separators (Zl, Zp), as of Unicode 15.
const FORMAT: &[std::ops::RangeInclusive<u32>] = &[
    0xAD..=0xAD,
    0x600..=0x605,
    0x61C..=0x61C,
    0x6DD..=0x6DD,
    0x70F..=0x70F,
    0x890..=0x891,
    0x8E2..=0x8E2,
    0x180E..=0x180E,
    0x200B..=0x200F,
    0x2028..=0x202E,
    0x2060..=0x2064,
    0x2066..=0x206F,
    0xFEFF..=0xFEFF,
    0xFFF9..=0xFFFB,
    0x110BD..=0x110BD,
    0x110CD..=0x110CD,
    0x13430..=0x1343F,
    0x1BCA0..=0x1BCA3,
    0x1D173..=0x1D17A,
    0xE0001..=0xE0001,
    0xE0020..=0xE007F,
];

/// Whether `c` would not show as itself on a terminal: a control or a format character.
pub fn unprintable(c: char) -> bool {
    c.is_control() || FORMAT.iter().any(|r| r.contains(&(c as u32)))
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

/// Priorities run from `-MAX_PRIORITY` to `MAX_PRIORITY`; 0 is the default.
pub const MAX_PRIORITY: i32 = 1000;

/// Refuses a priority outside `-MAX_PRIORITY..=MAX_PRIORITY`.
pub fn check_priority(priority: i32) -> Result<(), String> {
    if (-MAX_PRIORITY..=MAX_PRIORITY).contains(&priority) {
        Ok(())
    } else {
        Err(format!(
            "priority {priority} is outside -{MAX_PRIORITY}..={MAX_PRIORITY} (higher is served first; 0 is the default)"
        ))
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

/// Most confidence a stated error may claim: beyond it the bound rests on the far tail of the
/// normal approximation.
pub const MAX_CONFIDENCE: f32 = 0.999;

/// Refuses a confidence outside (0.5, [`MAX_CONFIDENCE`]] (0: none).
pub fn check_confidence(c: f32) -> Result<(), String> {
    if c == 0.0 || (c > 0.5 && c <= MAX_CONFIDENCE) {
        Ok(())
    } else {
        Err(format!("confidence {c} is not a probability above 0.5 and at most {MAX_CONFIDENCE} (e.g. 0.95)"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Controls and invisible format characters are refused in names and escaped in print;
    /// letters of any script, accents and emoji are names.
    #[test]
    fn names_refuse_controls_and_format_characters() {
        for bad in [
            "a\u{1b}[2J",
            "invoice\u{202e}fdp.exe",
            "zero\u{200b}width",
            "bom\u{feff}",
            "line\u{2028}sep",
            "tag\u{e0041}",
        ] {
            let e = check_name("a scene's name", bad).unwrap_err();
            assert!(e.contains("format characters"), "{e}");
            assert!(!e.chars().any(unprintable), "the refusal prints it raw: {e:?}");
        }
        for good in ["Café", "東京タワー", "scène 🎬 v2", "Ελληνικά", "עברית"] {
            assert!(check_name("a scene's name", good).is_ok(), "{good}");
            assert_eq!(crate::printable(good), good);
        }
        assert_eq!(crate::printable("a\u{202e}b"), "a\\u{202e}b");
    }

    /// A message is cut on a character boundary and says how much it left out.
    #[test]
    fn long_messages_are_clipped() {
        assert_eq!(clip("short", 10), "short");
        let long = "é".repeat(3000);
        let cut = clip(&long, MAX_MESSAGE_BYTES);
        assert!(cut.len() < MAX_MESSAGE_BYTES + 40 && cut.ends_with("é... (3952 more bytes)"), "{cut}");
    }

    /// A stored render's tile size reaches this check unbounded (a submission's is held to
    /// MAX_TILE_SIZE first): the largest is refused at once, naming the size that fits, without
    /// overflowing or searching four billion sides.
    #[test]
    fn any_tile_size_is_judged_without_overflow() {
        for features in [false, true] {
            let e = check_result_bytes(u32::MAX, features).unwrap_err();
            assert!(e.contains("use tiles of at most"), "{e}");
            let largest: u32 = e.rsplit(' ').nth(3).unwrap().parse().unwrap();
            assert!(
                check_result_bytes(largest, features).is_ok() && check_result_bytes(largest + 1, features).is_err()
            );
        }
    }
}
