//! Steering a render after submit: `tessera pause`, `resume` and `priority`.

use crate::client::{Connection, answer, block_on, state_of};
use anyhow::Result;
use clap::Args;
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::v1::SteerRequest;
use tessera_request::limits::MAX_PRIORITY;

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
