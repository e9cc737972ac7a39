//! Animation flags shared by the commands that render (`render`, `submit`): which animation
//! plays, and which moments of it become images (`--frame`, `--time`, `--frames`), with the
//! output names of a sequence.

use anyhow::{Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use tessera_render::plan::{FrameList, MAX_FRAME, frame_seed, frame_time};
use tessera_request::limits::{check_fps, check_time};
use tessera_request::{Frames, Pose};
use tessera_scene::PoseAt;
use tessera_scene::animation::Choice;

#[derive(Args, Clone, Debug, Default)]
pub struct AnimationArgs {
    /// Which of the scene's animations plays: its name or index, or "all" to play every animation
    /// on one clock [default: the first].
    #[arg(long, value_name = "NAME|INDEX|all", env = "TESSERA_ANIMATION")]
    pub animation: Option<String>,
    /// Render frame F: the scene at F / --fps seconds. Each frame draws its own samples.
    #[arg(long, value_name = "F", env = "TESSERA_FRAME", conflicts_with_all = ["time", "frames"], value_parser = clap::value_parser!(u32).range(0..=MAX_FRAME as i64))]
    pub frame: Option<u32>,
    /// Render a sequence of frames: 1-48, 1-48x2 (every second frame), 1,5,9, or a mix
    /// (at most 100,000 frames). Each frame is its own image.
    #[arg(long, value_name = "LIST", env = "TESSERA_FRAMES", conflicts_with = "time", value_parser = FrameList::parse)]
    pub frames: Option<FrameList>,
    /// Frames per second: frame F is the scene at F / FPS seconds.
    #[arg(long, default_value_t = 24.0, allow_negative_numbers = true, value_parser = parse_fps, env = "TESSERA_FPS")]
    pub fps: f64,
    /// Render the scene at this time, in seconds from the animation's start.
    #[arg(long, value_name = "SECONDS", env = "TESSERA_TIME", allow_negative_numbers = true, value_parser = parse_time)]
    pub time: Option<f64>,
}

fn parse_fps(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if check_fps(v).is_ok() => Ok(v),
        _ => Err(format!("'{s}' is not a positive number of frames per second")),
    }
}

fn parse_time(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if check_time(v).is_ok() => Ok(v),
        _ => Err(format!("'{s}' is not a time in seconds")),
    }
}

/// One image to render: the scene's pose (none: at rest, as stored), its frame number, and its
/// seed.
#[derive(Clone, Debug, PartialEq)]
pub struct Shot {
    pub pose: Option<PoseAt>,
    pub frame: Option<u32>,
    pub seed: u64,
}

impl AnimationArgs {
    /// Whether the flags ask for a sequence (several images).
    pub fn sequence(&self) -> bool {
        self.frames.is_some()
    }

    /// The images these flags ask for, seeded from `seed`: one at rest when no flag is given.
    pub fn shots(&self, seed: u64) -> Vec<Shot> {
        let choice = self.animation.as_deref().map(Choice::parse).unwrap_or_default();
        let at = |time: f32| Some(PoseAt { animation: choice.clone(), time });
        let frame = |f: u32| Shot { pose: at(frame_time(f, self.fps)), frame: Some(f), seed: frame_seed(seed, f) };
        match (&self.frames, self.frame, self.time) {
            (Some(list), _, _) => list.0.iter().map(|&f| frame(f)).collect(),
            (None, Some(f), _) => vec![frame(f)],
            (None, None, Some(t)) => vec![Shot { pose: at(t as f32), frame: None, seed }],
            (None, None, None) if self.animation.is_some() => vec![Shot { pose: at(0.0), frame: None, seed }],
            _ => vec![Shot { pose: None, frame: None, seed }],
        }
    }

    /// The pose of `shot` as a request carries it: where the animation is, and for a frame its
    /// number, the frame rate and the sequence's seed (`seed`), which label its image.
    pub fn pose(&self, shot: &Shot, seed: u64) -> Option<Pose> {
        shot.pose.as_ref().map(|p| Pose {
            animation: p.animation.clone(),
            time: p.time,
            frame: shot.frame,
            fps: if shot.frame.is_some() { self.fps } else { 0.0 },
            sequence_seed: seed,
        })
    }

    /// A sequence's frames as a farm takes them (the coordinator gives each its time and seed).
    pub fn frames(&self) -> Option<Frames> {
        self.frames.clone().map(|list| Frames { list, fps: self.fps })
    }
}

/// Where an image of `frame` goes: the run of `#`s in `out`'s file name replaced by the frame
/// number padded with zeros to its width (`shot.####.exr`, frame 7: `shot.0007.exr`).
pub fn frame_path(out: &Path, frame: Option<u32>) -> Result<PathBuf> {
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let Some(start) = name.find('#') else { return Ok(out.to_path_buf()) };
    let width = name[start..].chars().take_while(|&c| c == '#').count();
    if name[start + width..].contains('#') {
        bail!("{}: one run of #s marks the frame number, this name has two", out.display());
    }
    let Some(frame) = frame else {
        bail!("{}: the #s stand for a frame number; give --frame or --frames, or a name without #s", out.display())
    };
    let named = format!("{}{frame:0width$}{}", &name[..start], &name[start + width..]);
    Ok(out.with_file_name(named))
}

/// The output pattern of a render: `out` as given, or for a sequence without one
/// `render.####.exr`. A sequence must name its frames apart.
pub fn output_pattern(out: Option<&Path>, sequence: bool) -> Result<PathBuf> {
    match out {
        None if sequence => Ok(PathBuf::from("render.####.exr")),
        None => Ok(PathBuf::from("render.exr")),
        Some(p) if sequence && !p.file_name().is_some_and(|n| n.to_string_lossy().contains('#')) => bail!(
            "--out {}: a sequence needs #s in the file name for the frame number, as in shot.####.exr",
            p.display()
        ),
        Some(p) => Ok(p.to_path_buf()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_numbers_fill_the_hashes() {
        let p = |s: &str, f| frame_path(Path::new(s), f).map(|p| p.display().to_string());
        assert_eq!(p("out/shot.####.exr", Some(7)).unwrap(), "out/shot.0007.exr");
        assert_eq!(p("shot.#.exr", Some(123)).unwrap(), "shot.123.exr");
        assert_eq!(p("still.exr", Some(3)).unwrap(), "still.exr");
        assert!(p("a.##.#.exr", Some(1)).unwrap_err().to_string().contains("two"));
        assert!(p("a.##.exr", None).unwrap_err().to_string().contains("give --frame"));
        assert_eq!(output_pattern(None, true).unwrap(), PathBuf::from("render.####.exr"));
        assert!(output_pattern(Some(Path::new("x.exr")), true).unwrap_err().to_string().contains("needs #s"));
    }

    #[test]
    fn shots_follow_the_flags() {
        let args = |f: &dyn Fn(&mut AnimationArgs)| {
            let mut a = AnimationArgs { fps: 24.0, ..Default::default() };
            f(&mut a);
            a
        };
        assert_eq!(args(&|_| {}).shots(5), [Shot { pose: None, frame: None, seed: 5 }]);
        let one = args(&|a| a.frame = Some(48)).shots(5);
        assert_eq!(one[0].pose.as_ref().unwrap().time, 2.0);
        assert_eq!(one[0].seed, frame_seed(5, 48));
        let seq = args(&|a| a.frames = Some(FrameList(vec![1, 2]))).shots(5);
        assert_eq!(seq.len(), 2);
        assert_ne!(seq[0].seed, seq[1].seed);
        let t = args(&|a| a.time = Some(0.5)).shots(5);
        assert_eq!((t[0].frame, t[0].seed), (None, 5));
    }
}
