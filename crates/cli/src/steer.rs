//! Steering a render after submit: `tessera pause`, `resume` and `priority`; continuing a
//! finished one to a better quality: `tessera refine`; and reading what happened to it:
//! `tessera log`.

use crate::client::{Connection, answer, block_on, state_of};
use anyhow::{Result, bail};
use clap::Args;
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::v1::{LogRequest, RefineRequest, RenderRequest, RenderState, SteerRequest};
use tessera_request::limits::MAX_PRIORITY;
use tessera_request::printable;

#[derive(Args, Debug)]
pub struct PauseArgs {
    /// The render id, or a sequence's (s and a number): a sequence pauses as a whole.
    pub render: String,
    /// Hand its jobs in flight back at once, instead of letting them finish and merge (their
    /// passes are rendered again after the resume; the image is the same).
    #[arg(long, env = "TESSERA_NOW")]
    pub now: bool,
    #[command(flatten)]
    pub connection: Connection,
}

#[derive(Args, Debug)]
pub struct ResumeArgs {
    /// The render id, or a sequence's (s and a number).
    pub render: String,
    #[command(flatten)]
    pub connection: Connection,
}

#[derive(Args, Debug)]
pub struct PriorityArgs {
    /// The render id, or a sequence's (s and a number).
    pub render: String,
    /// The new priority, -1000 to 1000: higher is served first; 0 is the default.
    #[arg(allow_negative_numbers = true, value_parser = clap::value_parser!(i32).range(-(MAX_PRIORITY as i64)..=MAX_PRIORITY as i64))]
    pub priority: i32,
    #[command(flatten)]
    pub connection: Connection,
}

pub fn run_pause(args: PauseArgs) -> Result<()> {
    let request = SteerRequest { paused: Some(true), now: args.now, ..request(&args.render) };
    steer(&args.connection, request, "the pause")
}

pub fn run_resume(args: ResumeArgs) -> Result<()> {
    steer(&args.connection, SteerRequest { paused: Some(false), ..request(&args.render) }, "the resume")
}

pub fn run_priority(args: PriorityArgs) -> Result<()> {
    steer(&args.connection, SteerRequest { priority: Some(args.priority), ..request(&args.render) }, "the priority")
}

fn request(render: &str) -> SteerRequest {
    SteerRequest { protocol_version: PROTOCOL_VERSION, render_id: render.to_string(), ..SteerRequest::default() }
}

/// Sends `request` and says where the render stands now.
fn steer(connection: &Connection, request: SteerRequest, what: &str) -> Result<()> {
    block_on(async {
        let mut client = connection.connect().await?;
        let id = request.render_id.clone();
        let answered = answer(what, client.steer_render(request)).await?;
        match answered.status {
            Some(s) => eprintln!("render {id}: {}, priority {}", state_of(&s), s.priority),
            None => eprintln!("render {id}: changed"),
        }
        Ok(())
    })
}

#[derive(Args, Debug)]
pub struct LogArgs {
    /// The render id, or a sequence's (s and a number).
    pub render: String,
    /// Keep printing new lines until the render ends.
    #[arg(long, short, env = "TESSERA_FOLLOW")]
    pub follow: bool,
    /// One JSON object a line ({"at": seconds since the Unix epoch, "line": ...}), for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
    #[command(flatten)]
    pub connection: Connection,
}

/// `tessera log`: a render's stored log, each line with its time (UTC), and with `--follow`
/// the lines to come until it ends.
pub fn run_log(args: LogArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let mut after = 0;
        loop {
            let request = LogRequest { protocol_version: PROTOCOL_VERSION, render_id: args.render.clone(), after };
            let page = answer("the log", client.render_log(request)).await?;
            let mut out = String::new();
            if after == 0 && page.dropped > 0 && !args.json {
                out += &format!("({} older lines dropped)\n", page.dropped);
            }
            for l in &page.lines {
                after = after.max(l.id);
                if args.json {
                    out += &format!("{}\n", serde_json::json!({ "at": l.at, "line": l.line }));
                } else {
                    let at = std::time::UNIX_EPOCH + std::time::Duration::from_secs_f64(l.at.max(0.0));
                    out += &format!("{}  {}\n", humantime::format_rfc3339_seconds(at), printable(&l.line));
                }
            }
            crate::listing::print(&out)?;
            if !args.follow || (page.lines.is_empty() && ended(&mut client, &args.render).await?) {
                return Ok(());
            }
            tokio::time::sleep(std::time::Duration::from_secs(1)).await;
        }
    })
}

/// Whether render `id` has stopped running (done, failed or cancelled).
async fn ended(client: &mut crate::client::Client, id: &str) -> Result<bool> {
    let request =
        RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id.to_string(), frame: None, preview: false };
    let mut stream = answer("the render's status", client.watch_render(request)).await?;
    let status = tessera_client::next_within("with the render's status", &mut stream).await?;
    Ok(status.is_none_or(|s| s.state != RenderState::Running as i32))
}

#[derive(Args, Debug)]
pub struct RefineArgs {
    /// The finished render's id, or a finished sequence's (s and a number).
    pub render: String,
    /// Samples per pixel to continue to: at least the render's own.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=tessera_request::limits::MAX_SPP as i64), env = "TESSERA_SPP")]
    pub spp: Option<u32>,
    /// Relative error to continue to, at most the render's own (a render submitted with
    /// --target-error).
    #[arg(long, value_parser = tessera_local::options::parse_target_error, env = "TESSERA_TARGET_ERROR")]
    pub target_error: Option<f32>,
    #[command(flatten)]
    pub connection: Connection,
}

/// `tessera refine`: a finished render continued to a better quality; only the new passes
/// render, and the image is the bits of a render submitted with that quality.
pub fn run_refine(args: RefineArgs) -> Result<()> {
    let (spp, target_error) = (args.spp.unwrap_or(0), args.target_error.unwrap_or(0.0));
    if spp == 0 && target_error == 0.0 {
        bail!("nothing to refine: give --spp N (more samples per pixel) or --target-error E (a lower error)");
    }
    block_on(async {
        let mut client = args.connection.connect().await?;
        let request =
            RefineRequest { protocol_version: PROTOCOL_VERSION, render_id: args.render.clone(), spp, target_error };
        answer("the refinement", client.refine_render(request)).await?;
        eprintln!(
            "render {} continues: only its new passes render (`tessera watch {}` follows it, `tessera fetch {}` gets the image)",
            args.render, args.render, args.render
        );
        Ok(())
    })
}
