//! `tessera fetch`: a finished render's image, a sequence's finished frames, or their previews.

use crate::client::{Client, Connection, answer, block_on, fetch, next_of};
use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use tessera_local::animation::{frame_path, output_pattern};
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::v1::{FrameDone, RenderRequest};
use tessera_render::plan::FrameList;

#[derive(Args, Debug)]
pub struct FetchArgs {
    /// The render id, or a sequence's (s and a number).
    pub render: String,
    #[command(flatten)]
    pub connection: Connection,
    /// Output EXR path; #s in the name stand for the frame number.
    #[arg(long, default_value = "render.exr", env = "TESSERA_OUT")]
    pub out: PathBuf,
    /// The frame of a sequence to download.
    #[arg(long, value_name = "F", env = "TESSERA_FRAME", conflicts_with = "frames")]
    pub frame: Option<u32>,
    /// The frames of a sequence to download (e.g. 1-10, or 1-100x5): those finished of them.
    /// Without --frame or --frames, every finished frame of a sequence is downloaded.
    #[arg(long, value_name = "LIST", env = "TESSERA_FRAMES", value_parser = parse_frames)]
    pub frames: Option<FrameList>,
    /// The frames' preview images instead (a sequence submitted with --preview-every).
    #[arg(long, env = "TESSERA_PREVIEW")]
    pub preview: bool,
}

fn parse_frames(s: &str) -> Result<FrameList, String> {
    FrameList::parse(s)
}

pub fn run_fetch(args: FetchArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        if !args.render.starts_with('s') || args.frame.is_some() {
            if args.frames.is_some() {
                bail!("--frames picks frames of a sequence, and {} is a render: leave it out", args.render);
            }
            let out = frame_path(&args.out, args.frame)?;
            fetch(&mut client, &args.render, args.frame, args.preview, &out).await?;
            eprintln!("wrote {}", out.display());
            return Ok(());
        }
        // A sequence: every finished frame (of --frames), named by the #s in --out.
        output_pattern(Some(&args.out), true)?;
        let finished = finished_frames(&mut client, &args.render, args.preview).await?;
        let wanted: Vec<&FrameDone> =
            finished.iter().filter(|f| args.frames.as_ref().is_none_or(|l| l.0.contains(&f.frame))).collect();
        if wanted.is_empty() {
            bail!(
                "sequence {} has no finished frames{} yet: `tessera watch {}` follows it",
                args.render,
                if args.frames.is_some() { " of those asked for" } else { "" },
                args.render
            );
        }
        for f in &wanted {
            let out = frame_path(&args.out, Some(f.frame))?;
            fetch(&mut client, &f.render_id, None, args.preview, &out).await?;
            eprintln!("frame {}: wrote {}", f.frame, out.display());
        }
        if let Some(list) = &args.frames {
            let missing = list.0.iter().filter(|n| !finished.iter().any(|f| f.frame == **n)).count();
            if missing > 0 {
                eprintln!("{missing} of the frames asked for are not finished (or not in the sequence)");
            }
        }
        Ok(())
    })
}

/// The frames of sequence `id` finished so far (or with their preview written): the first
/// message of its watch lists them.
async fn finished_frames(client: &mut Client, id: &str, previews: bool) -> Result<Vec<FrameDone>> {
    let request =
        RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id.to_string(), frame: None, preview: false };
    let mut stream = answer("the list of finished frames", client.watch_render(request)).await?;
    let first = next_of("with the finished frames", &mut stream).await?;
    let mut frames = first.map(|s| if previews { s.previewed } else { s.finished }).unwrap_or_default();
    frames.sort_by_key(|f| f.frame);
    Ok(frames)
}
