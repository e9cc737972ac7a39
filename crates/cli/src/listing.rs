//! Text for standard output, which users pipe into `head` or `grep`. `println!` panics when the
//! reader has gone (a closed pipe); a listing written here just ends, as other Unix tools do.

use anyhow::{Context, Result};
use std::io::Write;

/// Writes `text` to standard output; a reader that stopped reading is not an error.
pub fn print(text: &str) -> Result<()> {
    let mut stdout = std::io::stdout().lock();
    match stdout.write_all(text.as_bytes()).and_then(|()| stdout.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        result => result.context("writing to standard output"),
    }
}
