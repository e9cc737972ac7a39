//! Accepting connections on every door (gRPC, dashboard, probes). Out of file handles, `accept`
//! fails at once for as long as a connection waits in the kernel's queue; a loop that retries at
//! once spins a core without a word (the probe measured 95-120 % CPU on the gRPC and metrics
//! doors). [`Acceptor`] waits after each failure, twice as long each time up to a second, and
//! logs the first failure of a run and every hundredth after it.

use std::net::SocketAddr;
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};

/// The wait after the first failed accept of a run.
pub const FIRST_WAIT: Duration = Duration::from_millis(5);
/// The longest wait between failed accepts.
pub const LONGEST_WAIT: Duration = Duration::from_secs(1);

/// The process's file handles are all in use (EMFILE), or the system's (ENFILE), as Linux
/// numbers them.
const EMFILE: i32 = 24;
const ENFILE: i32 = 23;

/// A listener whose failed accepts back off and are logged.
pub struct Acceptor {
    listener: TcpListener,
    door: &'static str,
    wait: Duration,
    failures: u64,
}

impl Acceptor {
    /// `door` names the listener in the log ("the gRPC door", "the dashboard").
    pub fn new(listener: TcpListener, door: &'static str) -> Self {
        Self { listener, door, wait: FIRST_WAIT, failures: 0 }
    }

    /// The next connection; failed accepts in between are waited out and logged.
    pub async fn accept(&mut self) -> (TcpStream, SocketAddr) {
        loop {
            match self.listener.accept().await {
                Ok(accepted) => {
                    if self.failures > 0 {
                        tracing::info!("{} accepts connections again after {} failures", self.door, self.failures);
                    }
                    self.failures = 0;
                    self.wait = FIRST_WAIT;
                    return accepted;
                }
                Err(e) => {
                    if self.failures.is_multiple_of(100) {
                        let hint = if matches!(e.raw_os_error(), Some(EMFILE | ENFILE)) {
                            " (out of file handles: raise `ulimit -n`, or lower --max-connections)"
                        } else {
                            ""
                        };
                        tracing::warn!(
                            "{} could not accept a connection ({} failed in a row): {e}{hint}",
                            self.door,
                            self.failures + 1
                        );
                    }
                    self.failures += 1;
                    tokio::time::sleep(self.wait).await;
                    self.wait = (self.wait * 2).min(LONGEST_WAIT);
                }
            }
        }
    }
}
