//! What both doors (gRPC and HTTP) do with a connection before any request is read: it takes a
//! place under its door's limit ([`Places`]; one past the limit is closed at once), and it is
//! closed when it is not admitted in time ([`FIRST_REQUEST`] for the gRPC door: an authenticated
//! request; the HTTP door's header timeout: a first byte) or, once admitted, when it is silent
//! too long. Without these, idle connections (which need no token to open) were kept for ever.

use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Sleep;
use tokio_stream::Stream;
use tonic::transport::server::{Connected, TcpConnectInfo, TlsConnectInfo};

/// How long a new gRPC connection may stay without an authenticated request.
pub const FIRST_REQUEST: Duration = Duration::from_secs(10);

/// Most connections one address may hold open before they are vouched for (have made a request
/// with a valid token) once its door is more than half full: a flood from one peer takes this many
/// of the places left, never all of them. Vouched connections do not count, and while the door has
/// room a peer is not counted at all (a farm's workers on one host, or a bench's, connect at once).
pub const PER_PEER_UNVOUCHED: usize = 32;

/// How many connections each address holds open without having been vouched for.
type Unvouched = Arc<std::sync::Mutex<std::collections::HashMap<std::net::IpAddr, usize>>>;

/// The places one door has for open connections.
pub struct Places {
    free: Arc<Semaphore>,
    limit: usize,
    unvouched: Unvouched,
    refused: AtomicU64,
    door: &'static str,
}

/// A connection's place under its door's limit, and (until it is vouched for) one of its
/// peer's [`PER_PEER_UNVOUCHED`].
pub struct Place {
    permit: OwnedSemaphorePermit,
    peer: Option<PeerSlot>,
}

/// One of a peer's unvouched places, given back when dropped.
#[derive(Debug)]
struct PeerSlot {
    peer: std::net::IpAddr,
    counts: Unvouched,
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        let mut counts = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = counts.get_mut(&self.peer) {
            *n -= 1;
            if *n == 0 {
                counts.remove(&self.peer);
            }
        }
    }
}

impl Places {
    pub fn new(door: &'static str, limit: usize) -> Arc<Self> {
        Arc::new(Self {
            free: Arc::new(Semaphore::new(limit.max(1))),
            limit,
            unvouched: Arc::default(),
            refused: AtomicU64::new(0),
            door,
        })
    }

    /// A place for a new connection from `peer`, held until dropped; `None` when every place is
    /// taken, or the door is more than half full and `peer` holds [`PER_PEER_UNVOUCHED`]
    /// connections no one vouched for (the connection is then to be closed at once, and the log
    /// says so once per hundred).
    pub fn take(&self, peer: Option<std::net::IpAddr>) -> Option<Place> {
        let slot = match peer {
            None => None,
            Some(peer) => {
                let mut counts = self.unvouched.lock().unwrap_or_else(|e| e.into_inner());
                let n = counts.entry(peer).or_default();
                let crowded = self.free.available_permits() < self.limit / 2;
                if *n >= PER_PEER_UNVOUCHED && crowded {
                    drop(counts);
                    self.refuse(&format!("{peer} holds {PER_PEER_UNVOUCHED} connections without a valid token"));
                    return None;
                }
                *n += 1;
                Some(PeerSlot { peer, counts: self.unvouched.clone() })
            }
        };
        match self.free.clone().try_acquire_owned() {
            Ok(permit) => Some(Place { permit, peer: slot }),
            Err(_) => {
                self.refuse(&format!("{} are open, the limit", self.limit));
                None
            }
        }
    }

    fn refuse(&self, why: &str) {
        if self.refused.fetch_add(1, Ordering::Relaxed).is_multiple_of(100) {
            tracing::warn!("the {} refused a connection: {why}", self.door);
        }
    }
}

/// Whether a connection has been admitted (made an authenticated request, or for the HTTP door
/// sent its first byte), and its peer's unvouched place while no one has vouched for it.
#[derive(Debug, Default)]
pub struct Admission {
    admitted: AtomicBool,
    unvouched: std::sync::Mutex<Option<PeerSlot>>,
}

impl Admission {
    fn admit(&self) {
        self.admitted.store(true, Ordering::Relaxed);
    }

    fn admitted(&self) -> bool {
        self.admitted.load(Ordering::Relaxed)
    }

    /// The connection made a request with a valid token: it no longer counts among its peer's
    /// unvouched connections.
    pub fn vouch(&self) {
        self.unvouched.lock().unwrap_or_else(|e| e.into_inner()).take();
    }
}

/// When a connection is closed for silence.
#[derive(Clone, Copy, Debug)]
pub struct Timers {
    /// Time to be admitted.
    pub admit_within: Duration,
    /// Admitted on its first byte (the HTTP door) rather than by an authenticated request.
    pub admit_on_first_byte: bool,
    /// Once admitted, the longest it may pass without a byte either way; `None`: no limit (the
    /// gRPC door, whose peers answer HTTP/2 pings and hold long polls).
    pub idle: Option<Duration>,
}

/// A connection under its door's limit and [`Timers`].
pub struct Guarded<S> {
    stream: S,
    _place: OwnedSemaphorePermit,
    admission: Arc<Admission>,
    timers: Timers,
    deadline: Pin<Box<Sleep>>,
}

impl<S> Guarded<S> {
    pub fn new(stream: S, place: Place, timers: Timers) -> Self {
        let deadline = Box::pin(tokio::time::sleep(timers.admit_within));
        let admission = Arc::new(Admission { admitted: AtomicBool::new(false), unvouched: place.peer.into() });
        Self { stream, _place: place.permit, admission, timers, deadline }
    }

    /// What the connection's requests may learn of it (the HTTP door vouches for it there).
    pub fn admission(&self) -> Arc<Admission> {
        self.admission.clone()
    }

    /// A byte went one way or the other.
    fn heard(&mut self) {
        if let Some(idle) = self.timers.idle
            && self.admission.admitted()
        {
            self.deadline.as_mut().reset(tokio::time::Instant::now() + idle);
        }
    }

    /// Whether the connection's time is up: not admitted in time, or (`idle`) silent too long.
    fn expired(&mut self, cx: &mut Context<'_>, idle: bool) -> Option<io::Error> {
        let admitted = self.admission.admitted();
        let watched = if idle { admitted && self.timers.idle.is_some() } else { !admitted };
        (watched && self.deadline.as_mut().poll(cx).is_ready()).then(|| {
            let why = if admitted {
                "the connection was silent too long".to_string()
            } else if self.timers.admit_on_first_byte {
                format!("no request within {} s of connecting", self.timers.admit_within.as_secs_f64())
            } else {
                format!("no authenticated request within {} s of connecting", self.timers.admit_within.as_secs())
            };
            io::Error::new(io::ErrorKind::TimedOut, why)
        })
    }
}

/// What a gRPC request learns of its connection (a request extension).
#[derive(Clone, Debug)]
pub struct ConnectionInfo {
    pub tcp: TcpConnectInfo,
    pub admission: Arc<Admission>,
}

fn connection_info<T>(request: &tonic::Request<T>) -> Option<&ConnectionInfo> {
    let ext = request.extensions();
    ext.get::<ConnectionInfo>().or_else(|| ext.get::<TlsConnectInfo<ConnectionInfo>>().map(|t| t.get_ref()))
}

/// Marks the connection of `request` as having made an authenticated request.
pub fn admit<T>(request: &tonic::Request<T>) {
    if let Some(info) = connection_info(request) {
        info.admission.admit();
        info.admission.vouch();
    }
}

/// The address `request` came from.
pub fn peer<T>(request: &tonic::Request<T>) -> Option<std::net::SocketAddr> {
    connection_info(request).and_then(|i| i.tcp.remote_addr())
}

impl Connected for Guarded<TcpStream> {
    type ConnectInfo = ConnectionInfo;
    fn connect_info(&self) -> ConnectionInfo {
        ConnectionInfo { tcp: self.stream.connect_info(), admission: self.admission.clone() }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Guarded<S> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        // A connection not admitted in time is closed whatever it sends meanwhile.
        if let Some(e) = self.expired(cx, false) {
            return Poll::Ready(Err(e));
        }
        let before = buf.filled().len();
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                if self.timers.admit_on_first_byte {
                    self.admission.admit();
                }
                self.heard();
                Poll::Ready(Ok(()))
            }
            Poll::Pending => match self.expired(cx, true) {
                Some(e) => Poll::Ready(Err(e)),
                None => Poll::Pending,
            },
            other => other,
        }
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Guarded<S> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        let written = Pin::new(&mut self.stream).poll_write(cx, buf);
        if matches!(written, Poll::Ready(Ok(n)) if n > 0) {
            self.heard();
        }
        written
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let written = Pin::new(&mut self.stream).poll_write_vectored(cx, bufs);
        if matches!(written, Poll::Ready(Ok(n)) if n > 0) {
            self.heard();
        }
        written
    }
    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

/// The gRPC door's connections: those `listener` accepts (failed accepts backing off, as on
/// every door: [`tessera_proto::accept`]), at most `limit` open at once, each closed if it makes
/// no authenticated request within [`FIRST_REQUEST`]. The listener is closed when the stream is
/// dropped.
pub fn guarded(listener: tokio::net::TcpListener, limit: usize) -> impl Stream<Item = io::Result<Guarded<TcpStream>>> {
    let places = Places::new("gRPC door", limit);
    let timers = Timers { admit_within: FIRST_REQUEST, admit_on_first_byte: false, idle: None };
    let mut acceptor = tessera_proto::accept::Acceptor::new(listener, "the gRPC door");
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(async move {
        loop {
            let stream = tokio::select! {
                (stream, _) = acceptor.accept() => stream,
                _ = tx.closed() => return,
            };
            let Some(place) = places.take(stream.peer_addr().ok().map(|a| a.ip())) else { continue };
            let _ = stream.set_nodelay(true);
            if tx.send(Ok(Guarded::new(stream, place, timers))).await.is_err() {
                return;
            }
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With its door more than half full, one peer holds at most [`PER_PEER_UNVOUCHED`] places
    /// until its connections are vouched for; another peer still gets in; a vouched connection,
    /// or a closed one, frees its peer's place but keeps (or frees) its door's.
    #[tokio::test]
    async fn one_peer_cannot_take_every_place() {
        let places = Places::new("test door", 60);
        let (a, b) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let timers = Timers { admit_within: Duration::from_secs(10), admit_on_first_byte: false, idle: None };
        let mut held: Vec<Guarded<()>> =
            (0..PER_PEER_UNVOUCHED).map(|_| Guarded::new((), places.take(Some(a)).unwrap(), timers)).collect();
        assert!(places.take(Some(a)).is_none(), "a took more than its share");
        assert!(places.take(Some(b)).is_some(), "another peer is locked out");
        held[0].admission().vouch();
        let vouched_again = places.take(Some(a)).expect("a vouched connection frees its peer's place");
        assert!(places.take(Some(a)).is_none());
        held.pop();
        assert!(places.take(Some(a)).is_some(), "a closed connection frees its peer's place");
        drop(vouched_again);
        // With room at the door, a peer is not counted.
        let roomy = Places::new("roomy door", 1000);
        let many: Vec<Place> = (0..2 * PER_PEER_UNVOUCHED).map_while(|_| roomy.take(Some(a))).collect();
        assert_eq!(many.len(), 2 * PER_PEER_UNVOUCHED);
        // The 31 still held (the vouched one among them) keep their door places.
        assert_eq!(places.free.available_permits(), 60 - (PER_PEER_UNVOUCHED - 1));
    }
}
