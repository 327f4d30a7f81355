//! The HTTP link under an S3 or WebDAV remote: reqwest, watched. Every body that crosses it, up
//! or down, reports its bytes to the [`Watch`] of the transfer that sent the request, so a
//! transfer is bounded by the wait for its next bytes (connect, first byte, each chunk either
//! way), never by its whole length, and an upload can show its progress.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body::{Body, Frame, SizeHint};
use object_store::ClientOptions;
use object_store::client::{HttpClient, HttpConnector, HttpError, HttpErrorKind, HttpRequest, HttpResponse, HttpResponseBody, HttpService};

/// The largest piece of a request body handed to the connection at once: an upload's progress
/// (and its watch) moves at least this often.
const SLICE: usize = 64 << 10;

/// Bytes a second: the slowest link a request body still in the kernel's buffers is waited for.
const SLOWEST_LINK: u64 = 64_000;

/// How often a watched transfer wakes to report its progress.
const TICK: Duration = Duration::from_millis(200);

/// When bytes last crossed the link for one transfer, and how many it has sent.
///
/// The connection hands a request body to the kernel's send buffer, which on a slow link holds
/// seconds of it (megabytes), and takes more only as the buffer drains: Linux wakes a writer once
/// a third of its buffer is free, so over a 1 MB/s link with 4 MiB buffers a body was taken in
/// bursts with 1.2-1.4 s of nothing between them while the link moved all along (measured: what
/// cut a 50 MB push at a 2 s timeout once in 11 runs, when the machine was busy). So once a
/// body's bytes are handed over, the wait for the next ones (or for the response, after its
/// last) may also last as long as they would take at [`SLOWEST_LINK`]; while the kernel still
/// holds unsent bytes, a link that stops taking them is cut by the kernel at the timeout
/// (`TCP_USER_TIMEOUT`, on Linux), so only a server that takes a whole body and never answers
/// costs the longer wait.
#[derive(Debug)]
pub(crate) struct Watch {
    origin: Instant,
    /// Milliseconds from `origin` to the last bytes.
    last: AtomicU64,
    sent: AtomicU64,
    /// Milliseconds the request body handed over so far would take at [`SLOWEST_LINK`], until
    /// its response (0 else).
    grace: AtomicU64,
}

impl Watch {
    pub(crate) fn new() -> Arc<Watch> {
        let zero = || AtomicU64::new(0);
        Arc::new(Watch { origin: Instant::now(), last: zero(), sent: zero(), grace: zero() })
    }

    fn now(&self) -> u64 {
        self.origin.elapsed().as_millis() as u64
    }

    fn touch(&self) {
        self.last.store(self.now(), Ordering::Relaxed);
    }

    fn idle(&self) -> Duration {
        self.origin.elapsed().saturating_sub(Duration::from_millis(self.last.load(Ordering::Relaxed)))
    }

    /// How long the transfer may stay quiet now, given the `limit` for a wait.
    fn allowed(&self, limit: Duration) -> Duration {
        limit + Duration::from_millis(self.grace.load(Ordering::Relaxed))
    }

    /// Request-body bytes handed to the connection so far.
    pub(crate) fn sent(&self) -> u64 {
        self.sent.load(Ordering::Relaxed)
    }
}

tokio::task_local! {
    /// The watch of the transfer whose requests the current task sends.
    static CURRENT: Arc<Watch>;
}

/// Runs `request` (whose HTTP requests report to `watch`) until it ends, or `None` once no bytes
/// crossed the link for `limit`; `tick` runs every [`TICK`] meanwhile.
pub(crate) async fn bounded<T>(watch: &Arc<Watch>, limit: Duration, request: impl Future<Output = T>, tick: &mut dyn FnMut(&Watch)) -> Option<T> {
    watch.touch();
    let mut request = std::pin::pin!(CURRENT.scope(watch.clone(), request));
    loop {
        match tokio::time::timeout(watch.allowed(limit).saturating_sub(watch.idle()).min(TICK), &mut request).await {
            Ok(value) => return Some(value),
            Err(_) => {
                tick(watch);
                if watch.idle() >= watch.allowed(limit) {
                    return None;
                }
            }
        }
    }
}

/// Whether `error` is the kernel cutting a connection whose sent bytes went unacknowledged for
/// the timeout (`TCP_USER_TIMEOUT`): a stalled link, as [`bounded`] finds one.
pub(crate) fn cut_by_the_kernel(error: &(dyn std::error::Error + 'static)) -> bool {
    std::iter::successors(Some(error), |e| e.source())
        .any(|e| e.downcast_ref::<std::io::Error>().is_some_and(|io| io.kind() == std::io::ErrorKind::TimedOut))
}

/// Makes object_store's HTTP clients: reqwest with a connect timeout of `timeout`, its bodies
/// watched, and no timeout of its own after that: reqwest's read timeout also runs while an
/// upload is still sending (the response is awaited meanwhile), so it would cut off a large
/// upload; [`bounded`] watches both directions instead. (It builds its own reqwest client, so
/// the builder's proxy and certificate options are not used; reqwest reads `HTTPS_PROXY` itself.)
#[derive(Debug)]
pub(crate) struct WatchedConnector {
    pub(crate) timeout: Duration,
}

impl HttpConnector for WatchedConnector {
    fn connect(&self, _: &ClientOptions) -> object_store::Result<HttpClient> {
        let builder = reqwest::Client::builder().user_agent(concat!("rlmflow/", env!("CARGO_PKG_VERSION"))).connect_timeout(self.timeout);
        // Where the kernel offers it (Linux), unacknowledged bytes cut the connection at the
        // timeout: what bounds a stall while a body drains from the kernel's buffer.
        #[cfg(any(target_os = "linux", target_os = "android", target_os = "fuchsia"))]
        let builder = builder.tcp_user_timeout(self.timeout);
        let client = builder.build().map_err(|e| object_store::Error::Generic { store: "HTTP", source: Box::new(e) })?;
        Ok(HttpClient::new(WatchedClient(client)))
    }
}

#[derive(Debug)]
struct WatchedClient(reqwest::Client);

impl HttpService for WatchedClient {
    fn call<'a, 'b>(&'a self, request: HttpRequest) -> Pin<Box<dyn Future<Output = Result<HttpResponse, HttpError>> + Send + 'b>>
    where
        'a: 'b,
        Self: 'b,
    {
        // A request sent outside a watched transfer (a credential lookup) gets a watch of its own.
        let watch = CURRENT.try_with(Arc::clone).unwrap_or_else(|_| Watch::new());
        Box::pin(async move {
            let (parts, body) = request.into_parts();
            let url = reqwest::Url::parse(&parts.uri.to_string()).map_err(|e| HttpError::new(HttpErrorKind::Request, e))?;
            let mut sent = reqwest::Request::new(parts.method, url);
            *sent.headers_mut() = parts.headers;
            *sent.body_mut() =
                Some(reqwest::Body::wrap(Watched { inner: body, pending: Bytes::new(), watch: watch.clone(), counts: true, taken: 0 }));
            let response = self.0.execute(sent).await.map_err(|e| HttpError::new(kind(&e), e))?;
            watch.grace.store(0, Ordering::Relaxed);
            watch.touch();
            let (parts, body) = http::Response::<reqwest::Body>::from(response).into_parts();
            let body = HttpResponseBody::new(Watched { inner: body, pending: Bytes::new(), watch, counts: false, taken: 0 });
            Ok(HttpResponse::from_parts(parts, body))
        })
    }
}

/// How object_store should treat a failed request (connect and timeout failures are retried).
fn kind(e: &reqwest::Error) -> HttpErrorKind {
    if e.is_timeout() {
        HttpErrorKind::Timeout
    } else if e.is_connect() {
        HttpErrorKind::Connect
    } else if e.is_request() {
        HttpErrorKind::Request
    } else {
        HttpErrorKind::Unknown
    }
}

/// A body whose frames touch `watch` as they pass, handed on in slices of at most [`SLICE`];
/// `counts`: its bytes are the transfer's sent bytes (a request body), `taken` of them so far.
struct Watched<B> {
    inner: B,
    pending: Bytes,
    watch: Arc<Watch>,
    counts: bool,
    taken: u64,
}

impl<B> Watched<B> {
    /// Request-body bytes were handed over: until the response the wait may also last as long as
    /// they would take at [`SLOWEST_LINK`] (see [`Watch`]).
    fn handed_over(&self) {
        if self.counts {
            self.watch.grace.store(self.taken * 1000 / SLOWEST_LINK, Ordering::Relaxed);
            self.watch.touch();
        }
    }
}

impl<B> Body for Watched<B>
where
    B: Body<Data = Bytes> + Unpin,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    type Data = Bytes;
    type Error = HttpError;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, HttpError>>> {
        let this = &mut *self;
        while this.pending.is_empty() {
            match Pin::new(&mut this.inner).poll_frame(cx) {
                Poll::Ready(Some(Ok(frame))) => match frame.into_data() {
                    Ok(data) => this.pending = data,
                    Err(trailers) => return Poll::Ready(Some(Ok(trailers))),
                },
                Poll::Ready(Some(Err(e))) => return Poll::Ready(Some(Err(HttpError::new_boxed(HttpErrorKind::Interrupted, e.into())))),
                Poll::Ready(None) => {
                    this.watch.touch();
                    return Poll::Ready(None);
                }
                Poll::Pending => return Poll::Pending,
            }
        }
        let slice = this.pending.split_to(this.pending.len().min(SLICE));
        this.watch.touch();
        if this.counts {
            this.watch.sent.fetch_add(slice.len() as u64, Ordering::Relaxed);
            this.taken += slice.len() as u64;
            this.handed_over();
        }
        Poll::Ready(Some(Ok(Frame::data(slice))))
    }

    fn is_end_stream(&self) -> bool {
        self.pending.is_empty() && self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        let inner = self.inner.size_hint();
        let pending = self.pending.len() as u64;
        let mut hint = SizeHint::new();
        hint.set_lower(inner.lower() + pending);
        if let Some(upper) = inner.upper() {
            hint.set_upper(upper + pending);
        }
        hint
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A body that knows it has ended only when asked for another frame, as a stream does.
    struct Streamed(Option<Bytes>);

    impl Body for Streamed {
        type Data = Bytes;
        type Error = std::io::Error;

        fn poll_frame(mut self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, std::io::Error>>> {
            Poll::Ready(self.0.take().map(|b| Ok(Frame::data(b))))
        }
    }

    fn watched(bytes: usize, watch: &Arc<Watch>) -> Watched<Streamed> {
        Watched { inner: Streamed(Some(Bytes::from(vec![0u8; bytes]))), pending: Bytes::new(), watch: watch.clone(), counts: true, taken: 0 }
    }

    /// What a request body handed over so far would take at the slowest link is the grace of
    /// the wait for the next bytes or the response, however the body ends.
    #[test]
    fn the_grace_grows_with_the_bytes_handed_over() {
        let watch = Watch::new();
        let mut body = watched(640_000, &watch);
        let mut cx = Context::from_waker(std::task::Waker::noop());
        let mut frames = 0;
        while let Poll::Ready(Some(frame)) = Pin::new(&mut body).poll_frame(&mut cx) {
            frame.unwrap();
            frames += 1;
            if frames == 5 {
                assert_eq!(watch.grace.load(Ordering::Relaxed), 5_120, "327,680 bytes handed over at 64 kB/s");
            }
        }
        assert_eq!(frames, 10, "handed over in slices of 64 kB");
        assert_eq!(watch.sent(), 640_000);
        assert_eq!(watch.grace.load(Ordering::Relaxed), 10_000, "640 kB at 64 kB/s: 10 s");
        assert_eq!(watch.allowed(Duration::from_secs(2)), Duration::from_secs(12));
    }

    /// The cause of a 50 MB push cut at its 2 s timeout over a 1 MB/s link: the connection took
    /// the body in bursts with 1.4 s of nothing between them (the kernel's buffer draining), and
    /// a busy machine stretched one past the timeout. Here the connection takes half a body,
    /// waits ten timeouts, then takes the rest: the transfer completes; a request that hands
    /// nothing over is still cut at the timeout.
    #[test]
    fn a_body_taken_in_bursts_is_not_cut_while_the_link_may_still_carry_what_it_took() {
        let runtime = tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap();
        let limit = Duration::from_millis(100);
        let watch = Watch::new();
        let mut body = watched(1_280_000, &watch);
        let connection = async {
            let mut frames = 0;
            while let Some(frame) = std::future::poll_fn(|cx| Pin::new(&mut body).poll_frame(cx)).await {
                frame.unwrap();
                frames += 1;
                if frames == 10 {
                    tokio::time::sleep(limit * 10).await;
                }
            }
            frames
        };
        assert_eq!(runtime.block_on(bounded(&watch, limit, connection, &mut |_| {})), Some(20), "the whole body, in two bursts");

        let started = std::time::Instant::now();
        let silent = async { tokio::time::sleep(limit * 10).await };
        assert_eq!(runtime.block_on(bounded(&Watch::new(), limit, silent, &mut |_| {})), None, "nothing handed over: cut");
        assert!(started.elapsed() < limit * 5, "cut at the timeout: {:?}", started.elapsed());
    }
}
