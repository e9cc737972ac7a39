//! Text for standard output, which users pipe into `head` or `grep`. On Unix, one-shot commands
//! end by SIGPIPE when the reader has gone, as other tools do (see `main`); elsewhere `println!`
//! would panic there, and a listing written here just ends.

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
