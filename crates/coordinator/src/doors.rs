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

/// The places one door has for open connections.
pub struct Places {
    free: Arc<Semaphore>,
    limit: usize,
    refused: AtomicU64,
    door: &'static str,
}

impl Places {
    pub fn new(door: &'static str, limit: usize) -> Arc<Self> {
        Arc::new(Self { free: Arc::new(Semaphore::new(limit.max(1))), limit, refused: AtomicU64::new(0), door })
    }

    /// A place for a new connection, held until dropped; `None` when every place is taken (the
    /// connection is then to be closed at once, and the log says so once per hundred).
    pub fn take(&self) -> Option<OwnedSemaphorePermit> {
        let place = self.free.clone().try_acquire_owned().ok();
        if place.is_none() && self.refused.fetch_add(1, Ordering::Relaxed).is_multiple_of(100) {
            tracing::warn!("the {} refused a connection: {} are open, the limit", self.door, self.limit);
        }
        place
    }
}

/// Whether a connection has been admitted (made an authenticated request, or for the HTTP door
/// sent its first byte).
#[derive(Debug, Default)]
pub struct Admission(AtomicBool);

impl Admission {
    fn admit(&self) {
        self.0.store(true, Ordering::Relaxed);
    }

    fn admitted(&self) -> bool {
        self.0.load(Ordering::Relaxed)
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
    pub fn new(stream: S, place: OwnedSemaphorePermit, timers: Timers) -> Self {
        let deadline = Box::pin(tokio::time::sleep(timers.admit_within));
        Self { stream, _place: place, admission: Arc::default(), timers, deadline }
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
            let Some(place) = places.take() else { continue };
            let _ = stream.set_nodelay(true);
            if tx.send(Ok(Guarded::new(stream, place, timers))).await.is_err() {
                return;
            }
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}
