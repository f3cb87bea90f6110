//! The live page's HTTP server: std's `TcpListener`, one thread per connection (at most
//! [`MAX_CONNECTIONS`]), a fixed route table, nothing read from disk but `report.html` and
//! `run.json` of the run's own out dir once the run ended.
//!
//! Safe by default: it binds loopback unless the user gave an address; every route is
//! read-only except `POST /stop`, which answers 403 unless `--view-allow-stop`; a request that
//! is not a well-formed HTTP/1.x GET/HEAD (or that POST) of a known path gets a 4xx and the
//! connection closes; on a loopback bind a `Host` header that names another host is refused
//! (a DNS-rebinding page cannot read the state). A connection's errors end that connection
//! only, never the run.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};

use super::Shared;

/// Connections served at once; more get 503.
pub const MAX_CONNECTIONS: usize = 32;
/// The request line and headers together, bytes.
const MAX_HEAD_BYTES: usize = 8 * 1024;
const READ_TIMEOUT: Duration = Duration::from_secs(5);
/// A reader that takes longer than this for one response is dropped.
const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// Server-sent events: at most one state per this interval (newer states replace older).
const EVENT_INTERVAL: Duration = Duration::from_millis(100);
/// A comment line on an idle event stream, so proxies and browsers keep it open.
const KEEPALIVE: Duration = Duration::from_secs(15);

const INDEX_HTML: &str = include_str!("page/index.html");
const APP_JS: &str = include_str!("page/app.js");
const STYLE_CSS: &str = include_str!("page/style.css");

/// What one server needs.
#[derive(Clone)]
pub struct Server {
    pub shared: Arc<Shared>,
    /// The run's out dir (report.html, run.json after the run).
    pub out: PathBuf,
    pub loopback_only: bool,
    pub port: u16,
    pub allow_stop: bool,
}

/// Accepts connections on a thread of its own.
pub fn spawn(listener: TcpListener, server: Server) -> Result<()> {
    let open = Arc::new(AtomicUsize::new(0));
    std::thread::Builder::new()
        .name("live-http".into())
        .spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { continue };
                if open.load(Ordering::SeqCst) >= MAX_CONNECTIONS {
                    let _ = stream.set_write_timeout(Some(WRITE_TIMEOUT));
                    let _ = respond(&mut stream, &plain(503, "too many connections"), false);
                    continue;
                }
                open.fetch_add(1, Ordering::SeqCst);
                let (mine, count) = (server.clone(), open.clone());
                let spawned =
                    std::thread::Builder::new()
                        .name("live-conn".into())
                        .spawn(move || {
                            mine.serve(stream);
                            count.fetch_sub(1, Ordering::SeqCst);
                        });
                if spawned.is_err() {
                    open.fetch_sub(1, Ordering::SeqCst);
                }
            }
        })
        .map(|_| ())
        .map_err(|e| anyhow!("cannot start the live page's server thread: {e}"))
}

/// A parsed request: what the routes need.
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    pub method: String,
    /// The path without the query.
    pub path: String,
    pub host: Option<String>,
}

/// Why a request is refused before routing.
#[derive(Debug, Clone, PartialEq)]
pub struct Refusal {
    pub status: u16,
    pub reason: &'static str,
}

/// Reads and checks the request head (request line and headers) from `r`.
pub fn read_request(r: &mut impl BufRead) -> std::result::Result<Request, Refusal> {
    let bad = |reason| Refusal {
        status: 400,
        reason,
    };
    let mut head = Vec::new();
    let mut lines = Vec::new();
    loop {
        let mut line = Vec::new();
        let n = r
            .take((MAX_HEAD_BYTES + 1 - head.len().min(MAX_HEAD_BYTES)) as u64)
            .read_until(b'\n', &mut line)
            .map_err(|_| bad("unreadable request"))?;
        if n == 0 {
            return Err(bad("incomplete request"));
        }
        head.extend_from_slice(&line);
        if head.len() > MAX_HEAD_BYTES {
            return Err(Refusal {
                status: 431,
                reason: "request head too large",
            });
        }
        if !line.ends_with(b"\n") {
            return Err(bad("incomplete request"));
        }
        let text = std::str::from_utf8(&line).map_err(|_| bad("request head is not UTF-8"))?;
        let text = text.trim_end_matches(['\r', '\n']);
        if text.is_empty() {
            if lines.is_empty() {
                continue; // tolerate blank lines before the request line (RFC 9112 2.2)
            }
            break;
        }
        lines.push(text.to_string());
    }
    let mut parts = lines[0].split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(bad("malformed request line"));
    };
    if !matches!(version, "HTTP/1.0" | "HTTP/1.1") {
        return Err(Refusal {
            status: 505,
            reason: "HTTP/1.0 or HTTP/1.1 only",
        });
    }
    if !target.starts_with('/') || target.bytes().any(|b| !(0x21..0x7f).contains(&b)) {
        return Err(bad("malformed request target"));
    }
    let path = target.split(['?', '#']).next().unwrap_or("/").to_string();
    let mut host = None;
    for h in &lines[1..] {
        let Some((name, value)) = h.split_once(':') else {
            return Err(bad("malformed header"));
        };
        if name.eq_ignore_ascii_case("host") {
            if host.is_some() {
                return Err(bad("two Host headers"));
            }
            host = Some(value.trim().to_string());
        }
    }
    Ok(Request {
        method: method.to_string(),
        path,
        host,
    })
}

/// True when `host` (a Host header) names this machine's loopback at `port`.
pub fn is_loopback_host(host: &str, port: u16) -> bool {
    let (name, p) = match host.rsplit_once(':') {
        Some((n, p)) if !n.ends_with(']') || n.starts_with('[') => (n, p.parse::<u16>().ok()),
        _ => (host, None),
    };
    let name_ok = matches!(name, "localhost" | "127.0.0.1" | "[::1]")
        || name
            .parse::<std::net::Ipv4Addr>()
            .is_ok_and(|a| a.is_loopback());
    name_ok && p.is_none_or(|p| p == port)
}

/// A response.
pub struct Response {
    pub status: u16,
    pub content_type: &'static str,
    pub body: Vec<u8>,
    pub extra: Vec<(String, String)>,
}

fn plain(status: u16, text: &str) -> Response {
    Response {
        status,
        content_type: "text/plain; charset=utf-8",
        body: format!("{status} {}: {text}\n", reason(status)).into_bytes(),
        extra: Vec::new(),
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        202 => "Accepted",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        409 => "Conflict",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        505 => "HTTP Version Not Supported",
        _ => "",
    }
}

fn respond(stream: &mut TcpStream, r: &Response, head_only: bool) -> std::io::Result<()> {
    let mut head = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-store\r\n\
         X-Content-Type-Options: nosniff\r\nConnection: close\r\n",
        r.status,
        reason(r.status),
        r.content_type,
        r.body.len()
    );
    for (k, v) in &r.extra {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    if !head_only {
        stream.write_all(&r.body)?;
    }
    stream.flush()
}

impl Server {
    fn serve(&self, mut stream: TcpStream) {
        let _ = stream.set_read_timeout(Some(READ_TIMEOUT));
        let _ = stream.set_write_timeout(Some(WRITE_TIMEOUT));
        let Ok(read_half) = stream.try_clone() else {
            return;
        };
        let req = read_request(&mut BufReader::new(read_half));
        let req = match req {
            Ok(r) => r,
            Err(refusal) => {
                let _ = respond(&mut stream, &plain(refusal.status, refusal.reason), false);
                return;
            }
        };
        if self.loopback_only
            && req
                .host
                .as_deref()
                .is_some_and(|h| !is_loopback_host(h, self.port))
        {
            let _ = respond(
                &mut stream,
                &plain(421, "this server answers to its loopback address only"),
                false,
            );
            return;
        }
        let head_only = req.method == "HEAD";
        if req.path == "/events" && req.method == "GET" {
            self.shared.update(|s| s.viewers.pages += 1);
            self.events(&mut stream);
            self.shared
                .update(|s| s.viewers.pages = s.viewers.pages.saturating_sub(1));
            return;
        }
        let r = self.route(&req);
        let _ = respond(&mut stream, &r, head_only);
    }

    /// The response to a (checked) request.
    pub fn route(&self, req: &Request) -> Response {
        let get = matches!(req.method.as_str(), "GET" | "HEAD");
        match (req.path.as_str(), get) {
            ("/stop", _) if req.method == "POST" => self.stop(),
            ("/stop", _) => plain(405, "POST only"),
            (_, false) => plain(405, "this page is read-only: GET and HEAD only"),
            ("/", true) | ("/index.html", true) => self.index(),
            ("/app.js", true) => asset("text/javascript; charset=utf-8", APP_JS),
            ("/style.css", true) => asset("text/css; charset=utf-8", STYLE_CSS),
            ("/state.json", true) => json(self.shared.lock().snapshot_text()),
            ("/preview.png", true) => self.preview_png(),
            ("/tile.png", true) => self.tile_png(),
            ("/report.html", true) => self.out_file("report.html", "text/html; charset=utf-8"),
            ("/run.json", true) => self.out_file("run.json", "application/json"),
            _ => plain(404, "no such page"),
        }
    }

    /// The page, with the current state inlined so that it draws at once (and a page saved
    /// or dumped shows the state it was served with).
    fn index(&self) -> Response {
        let state = self.shared.lock().snapshot_text();
        // JSON inside <script>: "</" must not close the element.
        let state = state.replace("</", "<\\/");
        Response {
            status: 200,
            content_type: "text/html; charset=utf-8",
            body: INDEX_HTML.replace("{{STATE}}", &state).into_bytes(),
            extra: vec![(
                "Content-Security-Policy".into(),
                "default-src 'self'; img-src 'self' blob: data:; script-src 'self'; \
                 style-src 'self'; connect-src 'self'; frame-ancestors 'none'"
                    .into(),
            )],
        }
    }

    fn stop(&self) -> Response {
        if !self.allow_stop {
            return plain(
                403,
                "stopping the run from the page is off (start the run with --view-allow-stop)",
            );
        }
        if self.shared.lock().run_ended {
            return plain(409, "the run has ended");
        }
        eprintln!("surfstream: stop requested from the live page");
        // The same path as Ctrl-C: the run stops through its failure path, FAILED says why.
        // SAFETY: raise(3) on this process.
        unsafe {
            libc::raise(libc::SIGINT);
        }
        plain(202, "stopping the run")
    }

    fn preview_png(&self) -> Response {
        let (heights, rows, cols, z0, extent) = {
            let s = self.shared.lock();
            let c = &s.canvas;
            if c.is_empty() {
                return plain(404, "no panorama yet");
            }
            let extent = format!(
                "{} {} {} {}",
                c.x0_um,
                c.y0_um,
                c.cols as f64 * c.cell_x_um,
                c.rows as f64 * c.cell_y_um
            );
            (c.heights.clone(), c.rows, c.cols, c.z0_um, extent)
        };
        let mut r = map_png(&heights, rows, cols, z0);
        r.extra.push(("X-Extent-Um".into(), extent));
        r
    }

    fn tile_png(&self) -> Response {
        let Some(tile) = self.shared.lock().newest_tile.clone() else {
            return plain(404, "no tile yet");
        };
        let h = tile.header;
        let mut r = map_png(
            &tile.heights,
            h.height as usize,
            h.width as usize,
            h.z_offset_um,
        );
        r.extra
            .push(("X-Tile-Index".into(), h.tile_index.to_string()));
        r
    }

    /// A file of the finished run's out dir: only these names, only after the run.
    fn out_file(&self, name: &str, content_type: &'static str) -> Response {
        if !self.shared.lock().run_ended {
            return plain(404, "the run has not ended yet");
        }
        match std::fs::read(self.out.join(name)) {
            Ok(body) => Response {
                status: 200,
                content_type,
                body,
                extra: Vec::new(),
            },
            Err(_) => plain(404, "the run wrote no such file"),
        }
    }

    /// Server-sent events: the whole state as one `state` event whenever it changed, at most
    /// one per [`EVENT_INTERVAL`]; a slow page gets the newest (skips counted).
    fn events(&self, stream: &mut TcpStream) {
        let head =
            "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n\
                    X-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\nretry: 1000\n\n";
        if stream.write_all(head.as_bytes()).is_err() {
            return;
        }
        let mut seen = u64::MAX;
        loop {
            let started = Instant::now();
            let (text, version, ended) = {
                let s = self.shared.wait_change(seen, KEEPALIVE);
                if s.version == seen {
                    drop(s);
                    if stream.write_all(b": keep-alive\n\n").is_err() {
                        return;
                    }
                    continue;
                }
                (s.snapshot_text(), s.version, s.run_ended)
            };
            if seen != u64::MAX && version > seen + 1 {
                self.shared.lock().drops.page_updates_skipped += version - seen - 1;
            }
            seen = version;
            let event = format!("event: state\nid: {version}\ndata: {text}\n\n");
            if stream.write_all(event.as_bytes()).is_err() || stream.flush().is_err() {
                return;
            }
            if ended && self.shared.lock().version == version {
                // Keep the stream until the process ends; nothing changes any more.
                drop(self.shared.wait_change(version, KEEPALIVE));
            }
            std::thread::sleep(EVENT_INTERVAL.saturating_sub(started.elapsed()));
        }
    }
}

fn asset(content_type: &'static str, text: &str) -> Response {
    Response {
        status: 200,
        content_type,
        body: text.as_bytes().to_vec(),
        extra: Vec::new(),
    }
}

fn json(text: String) -> Response {
    Response {
        status: 200,
        content_type: "application/json",
        body: text.into_bytes(),
        extra: Vec::new(),
    }
}

/// A height map (relative to `z0_um`) as an indexed viridis PNG over its robust range; the
/// range in absolute um goes in the `X-Height-Range-Um` header (the page draws the scale).
fn map_png(heights: &[f32], rows: usize, cols: usize, z0_um: f64) -> Response {
    let Some(range) = surfstream_io::preview::robust_range_um(heights) else {
        return plain(404, "nothing measured yet");
    };
    match surfstream_io::preview::encode_map_png(heights, rows, cols, 2048, range) {
        Ok(m) => Response {
            status: 200,
            content_type: "image/png",
            body: m.png,
            extra: vec![(
                "X-Height-Range-Um".into(),
                format!("{} {}", range.0 + z0_um, range.1 + z0_um),
            )],
        },
        Err(e) => plain(500, &format!("cannot draw the map: {e:#}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::live::state::LiveState;

    fn parse(text: &str) -> std::result::Result<Request, Refusal> {
        read_request(&mut std::io::Cursor::new(text.as_bytes().to_vec()))
    }

    fn server(allow_stop: bool) -> Server {
        Server {
            shared: Shared::new(LiveState::new("g", vec![(0, 0)], allow_stop)),
            out: std::env::temp_dir().join("surfstream-live-no-such-dir"),
            loopback_only: true,
            port: 8080,
            allow_stop,
        }
    }

    #[test]
    fn a_well_formed_get_is_parsed() {
        let r =
            parse("GET /state.json?x=1 HTTP/1.1\r\nHost: 127.0.0.1:8080\r\nAccept: */*\r\n\r\n")
                .unwrap();
        assert_eq!(r.method, "GET");
        assert_eq!(r.path, "/state.json");
        assert_eq!(r.host.as_deref(), Some("127.0.0.1:8080"));
    }

    #[test]
    fn hostile_requests_get_a_4xx() {
        let status = |t: &str| parse(t).map(|_| 200).unwrap_or_else(|r| r.status);
        assert_eq!(status(""), 400);
        assert_eq!(status("GET /\r\n\r\n"), 400);
        assert_eq!(status("GET / HTTP/1.1"), 400); // no end of head
        assert_eq!(status("GET / HTTP/2.0\r\n\r\n"), 505);
        assert_eq!(status("GET http://evil/ HTTP/1.1\r\n\r\n"), 400);
        assert_eq!(status("GET /a b HTTP/1.1\r\n\r\n"), 400);
        assert_eq!(status("GET /\x01 HTTP/1.1\r\n\r\n"), 400);
        assert_eq!(status("GET / HTTP/1.1\r\nnocolon\r\n\r\n"), 400);
        assert_eq!(status("GET / HTTP/1.1\r\nHost: a\r\nHost: b\r\n\r\n"), 400);
        let huge = format!(
            "GET / HTTP/1.1\r\nX: {}\r\n\r\n",
            "a".repeat(MAX_HEAD_BYTES)
        );
        assert_eq!(status(&huge), 431);
        let mut bytes = b"GET / HTTP/1.1\r\nX: \xff\xfe\r\n\r\n".to_vec();
        assert_eq!(
            read_request(&mut std::io::Cursor::new(std::mem::take(&mut bytes)))
                .unwrap_err()
                .status,
            400
        );
    }

    #[test]
    fn only_known_paths_are_served_and_nothing_from_disk_before_the_run_ended() {
        let s = server(false);
        let get = |p: &str| {
            s.route(&Request {
                method: "GET".into(),
                path: p.into(),
                host: None,
            })
            .status
        };
        assert_eq!(get("/"), 200);
        assert_eq!(get("/app.js"), 200);
        assert_eq!(get("/state.json"), 200);
        for p in [
            "/../../etc/passwd",
            "/report.html/../x",
            "/%2e%2e/run.json",
            "/logs/stage.stderr",
            "/nodes/matcher.json",
        ] {
            assert_eq!(get(p), 404, "{p}");
        }
        assert_eq!(get("/report.html"), 404);
        assert_eq!(get("/preview.png"), 404);
        assert_eq!(get("/tile.png"), 404);
        let post = |p: &str| {
            s.route(&Request {
                method: "POST".into(),
                path: p.into(),
                host: None,
            })
            .status
        };
        assert_eq!(post("/state.json"), 405);
        assert_eq!(post("/stop"), 403);
    }

    #[test]
    fn the_page_inlines_the_state_without_closing_its_script() {
        let s = server(false);
        s.shared.update(|st| st.graph = "</script><b>".into());
        let page = String::from_utf8(s.index().body).unwrap();
        assert!(page.contains(r#"<\/script><b>"#), "state not escaped");
        assert!(!page.contains("{{STATE}}"));
    }

    #[test]
    fn only_loopback_host_names_are_accepted_on_a_loopback_bind() {
        assert!(is_loopback_host("127.0.0.1:8080", 8080));
        assert!(is_loopback_host("localhost:8080", 8080));
        assert!(is_loopback_host("[::1]:8080", 8080));
        assert!(is_loopback_host("localhost", 8080));
        assert!(!is_loopback_host("localhost:9090", 8080));
        assert!(!is_loopback_host("evil.example:8080", 8080));
        assert!(!is_loopback_host("127.0.0.1.evil.example:8080", 8080));
    }
}
