//! The coordinator's doors: every accepted TCP connection takes a place under a limit, and one
//! that has not made an authenticated request within [`FIRST_REQUEST`] of opening is closed.
//! Without this, idle connections (which need no token to open) were kept for ever.

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
use tokio_stream::{Stream, StreamExt};
use tonic::transport::server::{Connected, TcpConnectInfo, TlsConnectInfo};

/// How long a new connection may stay without an authenticated request.
pub const FIRST_REQUEST: Duration = Duration::from_secs(10);

/// Whether a connection has made an authenticated request.
#[derive(Debug, Default)]
pub struct Admission(AtomicBool);

/// What a request learns of its connection (a request extension).
#[derive(Clone, Debug)]
pub struct ConnectionInfo {
    pub tcp: TcpConnectInfo,
    pub admission: Arc<Admission>,
}

/// Marks the connection of `request` as having made an authenticated request.
pub fn admit<T>(request: &tonic::Request<T>) {
    let ext = request.extensions();
    let info = ext.get::<ConnectionInfo>().or_else(|| ext.get::<TlsConnectInfo<ConnectionInfo>>().map(|t| t.get_ref()));
    if let Some(info) = info {
        info.admission.0.store(true, Ordering::Relaxed);
    }
}

/// The address `request` came from.
pub fn peer<T>(request: &tonic::Request<T>) -> Option<std::net::SocketAddr> {
    let ext = request.extensions();
    let info = ext.get::<ConnectionInfo>().or_else(|| ext.get::<TlsConnectInfo<ConnectionInfo>>().map(|t| t.get_ref()));
    info.and_then(|i| i.tcp.remote_addr())
}

/// An accepted connection under the limit.
pub struct Guarded {
    stream: TcpStream,
    _place: OwnedSemaphorePermit,
    admission: Arc<Admission>,
    deadline: Pin<Box<Sleep>>,
}

impl Connected for Guarded {
    type ConnectInfo = ConnectionInfo;
    fn connect_info(&self) -> ConnectionInfo {
        ConnectionInfo { tcp: self.stream.connect_info(), admission: self.admission.clone() }
    }
}

impl AsyncRead for Guarded {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        if !self.admission.0.load(Ordering::Relaxed) && self.deadline.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no authenticated request within {} s of connecting", FIRST_REQUEST.as_secs()),
            )));
        }
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
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
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }
    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

/// The connections `listener` accepts, at most `limit` open at once: one past the limit is
/// closed at once (and counted in `refused`), so that a flood of connections cannot take the
/// coordinator's memory or file descriptors.
pub fn guarded(
    listener: tokio::net::TcpListener,
    limit: usize,
    refused: Arc<AtomicU64>,
) -> impl Stream<Item = io::Result<Guarded>> {
    let places = Arc::new(Semaphore::new(limit.max(1)));
    tokio_stream::wrappers::TcpListenerStream::new(listener).filter_map(move |accepted| {
        let stream = match accepted {
            Ok(s) => s,
            Err(e) => return Some(Err(e)),
        };
        let Ok(place) = places.clone().try_acquire_owned() else {
            // Said once per hundred, so that a flood does not flood the log too.
            if refused.fetch_add(1, Ordering::Relaxed).is_multiple_of(100) {
                tracing::warn!("refused a connection: {limit} are open, the limit (--max-connections)");
            }
            return None;
        };
        let _ = stream.set_nodelay(true);
        let deadline = Box::pin(tokio::time::sleep(FIRST_REQUEST));
        Some(Ok(Guarded { stream, _place: place, admission: Arc::default(), deadline }))
    })
}
