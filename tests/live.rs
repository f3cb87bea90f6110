//! The live view (issue 34), end to end: the demo graph at the instrument's pace (`stage.pacing`
//! real time, 3 x 3 fields; 256 px tiles keep it cheap) with `--view`, watched by a headless
//! Chromium while it scans, and with `--foxglove`, watched by a WebSocket client speaking the
//! Foxglove protocol (the Python `websockets` package of the test venv). And the two things
//! a viewer must see before the end: a replayed recording's plan (tiles planned, ETA) from its
//! first tile, and each pair's registration (NCC, weak link, residual) as the matcher decides
//! it.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use surfstream_e2e::{python, run, surfstream};

const CHROMIUM: &str = "/usr/bin/chromium";

/// A run started in the background, its stderr collected (and echoed to the test log).
struct Run {
    child: Child,
    stderr: Arc<Mutex<String>>,
}

impl Run {
    fn start(out: &Path, rows: u32, field_time_s: f64, extra: &[&str]) -> Run {
        let mut cmd = surfstream();
        cmd.args(["launch", "launch/graphs/demo.toml", "-o"])
            .arg(out)
            .args(["--set", &format!("stage.rows={rows}")])
            .args(["--set", "stage.cols=3", "--set", "stage.tile_px=256"])
            .args(["--set", "stage.pacing=\"realtime\""])
            .args(["--set", &format!("stage.field_time_s={field_time_s}")])
            .args(extra);
        Run::spawn(cmd)
    }

    /// Starts `cmd` with its stdout and stderr collected.
    fn spawn(mut cmd: Command) -> Run {
        cmd.stdout(Stdio::piped()).stderr(Stdio::piped());
        let mut child = cmd.spawn().expect("start surfstream launch");
        let stderr = Arc::new(Mutex::new(String::new()));
        let pipe = child.stderr.take().expect("stderr");
        let sink = stderr.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines().map_while(Result::ok) {
                eprintln!("| {line}");
                let mut s = sink.lock().unwrap();
                s.push_str(&line);
                s.push('\n');
            }
        });
        Run { child, stderr }
    }

    /// The URL printed after `prefix` on stderr (waits up to 60 s).
    fn url(&mut self, prefix: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(url) = self
                .stderr
                .lock()
                .unwrap()
                .lines()
                .find_map(|l| l.split(prefix).nth(1))
                .and_then(|rest| rest.split_whitespace().next())
            {
                return url.to_string();
            }
            assert!(
                self.child.try_wait().unwrap().is_none(),
                "the run ended before printing '{prefix}':\n{}",
                self.stderr.lock().unwrap()
            );
            assert!(Instant::now() < deadline, "no '{prefix}' line within 60 s");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits for the process; returns its stdout (the verdict).
    fn wait(mut self) -> (std::process::ExitStatus, String) {
        let mut stdout = String::new();
        if let Some(mut s) = self.child.stdout.take() {
            let _ = s.read_to_string(&mut stdout);
        }
        (self.child.wait().expect("wait"), stdout)
    }
}

/// `METHOD path` on the live server: status and body (raw bytes sent as given).
fn request(url: &str, raw: &str) -> (u16, Vec<u8>) {
    let host = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_string();
    let mut s = TcpStream::connect(&host).expect("connect to the live view");
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    s.write_all(raw.replace("{host}", &host).as_bytes())
        .unwrap();
    let mut reply = Vec::new();
    let _ = s.read_to_end(&mut reply);
    let head_end = reply
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .unwrap_or(reply.len());
    let head = String::from_utf8_lossy(&reply[..head_end]).to_string();
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status line in {head:?}"));
    (status, reply[(head_end + 4).min(reply.len())..].to_vec())
}

fn get(url: &str, path: &str) -> (u16, Vec<u8>) {
    request(
        url,
        &format!("GET {path} HTTP/1.1\r\nHost: {{host}}\r\nConnection: close\r\n\r\n"),
    )
}

fn state(url: &str) -> serde_json::Value {
    let (status, body) = get(url, "/state.json");
    assert_eq!(status, 200);
    serde_json::from_slice(&body).expect("state.json is JSON")
}

/// Headless Chromium: a screenshot of `url` and its DOM after load.
fn chromium(url: &str, screenshot: &Path) -> String {
    let profile = tempfile::tempdir().unwrap();
    let out = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--window-size=1400,1000",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(format!("--screenshot={}", screenshot.display()))
        .arg("--dump-dom")
        .arg(url)
        .stderr(Stdio::null())
        .output()
        .expect("start chromium");
    assert!(out.status.success(), "chromium failed: {:?}", out.status);
    String::from_utf8_lossy(&out.stdout).to_string()
}

/// Elements of the DOM carrying `attr` (`data-tile="..."`).
fn count_attr(dom: &str, attr: &str) -> usize {
    dom.matches(&format!("{attr}=\"")).count()
}

/// The value of `attr` on the body element.
fn body_attr(dom: &str, attr: &str) -> Option<String> {
    let body = &dom[dom.find("<body")?..];
    let body = &body[..body.find('>')?];
    let at = body.find(&format!("{attr}=\""))? + attr.len() + 2;
    Some(body[at..at + body[at..].find('"')?].to_string())
}

#[test]
fn the_live_page_shows_the_tiles_registered_so_far_and_then_the_final_verdict() {
    if !Path::new(CHROMIUM).exists() {
        eprintln!("SKIPPED: {CHROMIUM} is not installed (CI installs the Debian package chromium)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    // 2 s per field: Chromium on a loaded 2-core machine needs seconds to start.
    let mut run = Run::start(&out, 3, 2.0, &["--view", "--view-linger-s", "60"]);
    let url = run.url("live view at ");
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");

    // Mid-scan: some but not all of the 9 tiles registered.
    let deadline = Instant::now() + Duration::from_secs(120);
    let before = loop {
        let s = state(&url);
        assert_eq!(s["tiles_planned"], 9);
        let n = s["tiles_registered"].as_u64().unwrap();
        if (2..9).contains(&n) {
            assert_eq!(s["verdict"], serde_json::Value::Null, "no verdict mid-scan");
            break n;
        }
        assert!(n < 9, "the scan finished before the test saw it mid-way");
        assert!(Instant::now() < deadline, "no tile registered within 120 s");
        std::thread::sleep(Duration::from_millis(100));
    };
    let shot = dir.path().join("live.png");
    let dom = chromium(&url, &shot);
    let after = state(&url)["tiles_registered"].as_u64().unwrap();
    let boxes = count_attr(&dom, "data-tile");
    let served: usize = body_attr(&dom, "data-tiles-registered")
        .expect("the page says how many tiles it drew")
        .parse()
        .unwrap();
    eprintln!("tiles registered: {before} before the page, {boxes} boxes on it, {after} after");
    assert_eq!(
        boxes, served,
        "one box per registered tile of the state the page was served with"
    );
    assert!(
        before as usize <= boxes && boxes as u64 <= after,
        "{before} <= {boxes} <= {after}"
    );
    assert!(boxes < 9, "the page was taken mid-scan");
    // Every box is a placement class the legend names.
    assert_eq!(
        dom.matches("class=\"tile registration\"").count()
            + dom.matches("class=\"tile weak_link\"").count()
            + dom.matches("class=\"tile stage_fallback\"").count(),
        boxes
    );
    let png = std::fs::read(&shot).expect("the screenshot");
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 10_000);
    if let Ok(keep) = std::env::var("SURFSTREAM_LIVE_SCREENSHOT") {
        std::fs::copy(&shot, &keep).expect("copy the screenshot");
    }

    // Hostile or malformed requests get a 4xx; the run goes on.
    let status = |raw: &str| request(&url, raw).0;
    assert_eq!(status("GARBAGE\r\n\r\n"), 400);
    assert_eq!(status("GET /../../etc/passwd HTTP/1.1\r\n\r\n"), 404);
    assert_eq!(status("GET /logs/stage.stderr HTTP/1.1\r\n\r\n"), 404);
    assert_eq!(
        status("POST /stop HTTP/1.1\r\nContent-Length: 0\r\n\r\n"),
        403
    );
    assert_eq!(status("DELETE /state.json HTTP/1.1\r\n\r\n"), 405);
    assert_eq!(
        status("GET /state.json HTTP/1.1\r\nHost: rebind.example:80\r\n\r\n"),
        421
    );
    assert_eq!(
        status(&format!("GET /{} HTTP/1.1\r\n\r\n", "a".repeat(20_000))),
        431
    );
    assert_eq!(
        get(&url, "/report.html").0,
        404,
        "no report before the run ended"
    );

    // After the run: the final verdict, the CLI's own, and the report.
    let deadline = Instant::now() + Duration::from_secs(300);
    let fin = loop {
        let s = state(&url);
        if !s["verdict"].is_null() {
            break s;
        }
        assert!(Instant::now() < deadline, "no verdict within 300 s");
        std::thread::sleep(Duration::from_millis(250));
    };
    assert_eq!(fin["tiles_registered"], 9);
    assert!(fin["run_ended"].as_bool().unwrap());
    let verdict = fin["verdict"].as_str().unwrap().to_string();
    let dom = chromium(&url, &dir.path().join("final.png"));
    assert_eq!(
        body_attr(&dom, "data-verdict").as_deref(),
        Some(verdict.as_str())
    );
    assert_eq!(count_attr(&dom, "data-tile"), 9);
    let (status, report) = get(&url, "/report.html");
    assert_eq!(status, 200);
    assert_eq!(report, std::fs::read(out.join("report.html")).unwrap());
    // Stop the linger (Ctrl-C ends it) and compare with what the CLI printed.
    unsafe {
        libc::kill(run.child.id() as libc::pid_t, libc::SIGINT);
    }
    let (exit, stdout) = run.wait();
    assert!(exit.success(), "{exit:?}");
    let failures = fin["failures"].as_array().unwrap();
    assert_eq!(verdict == "PASS", failures.is_empty(), "{failures:?}");
    let text = fin["verdict_text"].as_str().unwrap();
    // The same lines as the CLI's verdict (whose first line adds the wall time).
    let tail = |t: &str| t.lines().skip(1).map(str::to_string).collect::<Vec<_>>();
    assert_eq!(tail(text), tail(stdout.trim_end()));
}

/// A Foxglove WebSocket client: subscribes to every channel and prints, as JSON, the first
/// `/tiles` message it receives.
const FOXGLOVE_CLIENT: &str = r#"
import asyncio, json, struct, sys, base64
import websockets

async def main(url):
    async with websockets.connect(url, subprotocols=["foxglove.websocket.v1"], max_size=None) as ws:
        assert ws.subprotocol == "foxglove.websocket.v1", ws.subprotocol
        info = json.loads(await ws.recv())
        assert info["op"] == "serverInfo", info
        adv = json.loads(await ws.recv())
        assert adv["op"] == "advertise", adv
        channels = {c["id"]: c for c in adv["channels"]}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 10 + i, "channelId": c} for i, c in enumerate(channels)]}))
        by_sub = {10 + i: channels[c] for i, c in enumerate(channels)}
        seen = set()
        while True:
            m = await ws.recv()
            if isinstance(m, str):
                continue
            op, sub, t_ns = struct.unpack_from("<BIQ", m, 0)
            assert op == 1, op
            ch = by_sub[sub]
            seen.add(ch["topic"])
            if ch["topic"] == "/tiles":
                grid = json.loads(m[13:])
                cells = base64.b64decode(grid["data"])
                print(json.dumps({
                    "schemaName": ch["schemaName"], "encoding": ch["encoding"],
                    "column_count": grid["column_count"], "row_stride": grid["row_stride"],
                    "cell_bytes": len(cells), "kind": grid["surfstream"]["kind"],
                    "tile_index": grid["surfstream"]["tile_index"],
                    "height": grid["surfstream"]["height"], "fields": grid["fields"],
                    "topics": sorted(seen)}))
                return

asyncio.run(asyncio.wait_for(main(sys.argv[1]), 120))
"#;

#[test]
fn a_foxglove_client_receives_tile_grids_during_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let mut run = Run::start(&dir.path().join("out"), 2, 1.0, &["--foxglove"]);
    let url = run.url("Foxglove live stream at ");
    assert!(url.starts_with("ws://127.0.0.1:"), "{url}");
    let client = Command::new(python())
        .arg("-c")
        .arg(FOXGLOVE_CLIENT)
        .arg(&url)
        .output()
        .expect("start the Python WebSocket client");
    let during = run.child.try_wait().unwrap().is_none();
    assert!(
        client.status.success(),
        "the client failed:\n{}",
        String::from_utf8_lossy(&client.stderr)
    );
    let got: serde_json::Value =
        serde_json::from_slice(&client.stdout).expect("the client's JSON line");
    eprintln!("first /tiles message: {got}");
    assert!(during, "the tile arrived while the run was still going");
    assert_eq!(got["schemaName"], "foxglove.Grid");
    assert_eq!(got["encoding"], "json");
    assert_eq!(got["kind"], 1, "a tile frame");
    assert_eq!(got["column_count"], 256);
    assert_eq!(got["height"], 256);
    assert_eq!(got["row_stride"], 256 * 4);
    assert_eq!(got["cell_bytes"], 256 * 256 * 4);
    assert_eq!(got["fields"][0]["name"], "height_um");
    let (exit, _) = run.wait();
    assert!(exit.success(), "{exit:?}");
}

/// The page's text of the element with `id` (`<span id="planned">9</span>`).
fn element_text(dom: &str, id: &str) -> Option<String> {
    let at = dom.find(&format!("id=\"{id}\""))?;
    let rest = &dom[at..];
    let start = rest.find('>')? + 1;
    let end = rest[start..].find('<')? + start;
    Some(rest[start..end].to_string())
}

/// A Foxglove WebSocket client: subscribes to `/progress` and prints its first message.
const FOXGLOVE_PROGRESS: &str = r#"
import asyncio, json, struct, sys
import websockets

async def main(url):
    async with websockets.connect(url, subprotocols=["foxglove.websocket.v1"], max_size=None) as ws:
        json.loads(await ws.recv())
        adv = json.loads(await ws.recv())
        ch = [c for c in adv["channels"] if c["topic"] == "/progress"][0]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": ch["id"]}]}))
        while True:
            m = await ws.recv()
            if isinstance(m, bytes):
                op, sub, _ = struct.unpack_from("<BIQ", m, 0)
                msg = json.loads(m[13:])
                msg["schemaName"] = ch["schemaName"]
                print(json.dumps(msg))
                return

asyncio.run(asyncio.wait_for(main(sys.argv[1]), 120))
"#;

/// Polls `/state.json` until `until` holds (or panics after `secs` seconds).
fn wait_state(
    url: &str,
    secs: u64,
    what: &str,
    mut until: impl FnMut(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let s = state(url);
        if until(&s) {
            return s;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: not within {secs} s; last state {s}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_replayed_recording_shows_its_plan_from_its_first_tile() {
    let dir = tempfile::tempdir().unwrap();
    // A recording at the instrument's pace (the demo graph records the stage's tiles).
    let rec = dir.path().join("rec");
    let mut cmd = surfstream();
    cmd.args(["run", "launch/graphs/demo.toml", "-o"])
        .arg(&rec)
        .args([
            "--set",
            "stage.rows=3",
            "--set",
            "stage.cols=3",
            "--set",
            "stage.tile_px=256",
        ])
        .args([
            "--set",
            "stage.pacing=\"realtime\"",
            "--set",
            "stage.field_time_s=2.0",
        ]);
    let out = run(cmd);
    assert!(out.status.success());
    let recording = rec.join("recording.mcap");
    assert!(recording.is_file());

    // Replayed at its recorded pace, with the page and Foxglove.
    let mut cmd = surfstream();
    cmd.args(["launch", "launch/graphs/replay.toml", "-o"])
        .arg(dir.path().join("replay"))
        .arg("--set")
        .arg(format!("stage.path=\"{}\"", recording.display()))
        .args(["--view", "--foxglove", "--view-linger-s", "60"]);
    let mut replay = Run::spawn(cmd);
    let url = replay.url("live view at ");
    let ws = replay.url("Foxglove live stream at ");
    // The plan is known as soon as the view has the graph (the recording's summary), before
    // the replay's first tile, and stays.
    let first = wait_state(&url, 60, "the graph attached", |s| s["graph"] != "");
    eprintln!(
        "first state: {} tiles registered",
        first["tiles_registered"]
    );
    assert_eq!(first["tiles_planned"], 9, "{first}");
    let mid = wait_state(&url, 120, "two of the nine tiles registered", |s| {
        assert_eq!(s["tiles_planned"], 9);
        let n = s["tiles_registered"].as_u64().unwrap();
        assert!(n < 9, "the replay finished before the test saw it mid-way");
        n >= 2
    });
    assert!(
        mid["progress"]["eta_s"].as_f64().is_some_and(|e| e > 0.0),
        "an ETA mid-scan: {mid}"
    );
    assert!(mid["progress"]["fields_per_s"]
        .as_f64()
        .is_some_and(|f| f > 0.0));
    let dom = chromium(&url, &dir.path().join("replay.png"));
    assert_eq!(
        element_text(&dom, "planned").as_deref(),
        Some("9"),
        "done / planned on the page"
    );
    assert_ne!(
        element_text(&dom, "eta").as_deref(),
        Some("-"),
        "an ETA on the page"
    );
    let client = Command::new(python())
        .arg("-c")
        .arg(FOXGLOVE_PROGRESS)
        .arg(&ws)
        .output()
        .expect("start the Python WebSocket client");
    assert!(
        client.status.success(),
        "the client failed:\n{}",
        String::from_utf8_lossy(&client.stderr)
    );
    let progress: serde_json::Value = serde_json::from_slice(&client.stdout).expect("a JSON line");
    eprintln!("Foxglove /progress: {progress}");
    assert_eq!(progress["schemaName"], "surfstream.Progress");
    assert_eq!(progress["tiles_planned"], 9);
    let fin = wait_state(&url, 300, "the verdict", |s| !s["verdict"].is_null());
    assert_eq!(fin["tiles_registered"], 9);
    assert_eq!(fin["progress"]["eta_s"], 0.0);
    unsafe {
        libc::kill(replay.child.id() as libc::pid_t, libc::SIGINT);
    }
    let console = replay.stderr.clone();
    let (exit, _) = replay.wait();
    assert!(exit.success(), "{exit:?}");
    // The console's progress lines (printed while the tiles came) count against the plan.
    let err = console.lock().unwrap().clone();
    assert!(err.contains("/9 ("), "no 'tile N/9' progress line: {err}");
}

#[test]
fn each_pair_and_its_weak_link_show_while_the_matcher_decides_them() {
    let dir = tempfile::tempdir().unwrap();
    // An NCC floor no pair reaches: every accepted pair is a distinct peak below it, a weak
    // link (the others are refused, their tiles placed by the stage).
    // 4 s a field: the page is rendered by a headless chromium after the weak link shows,
    // which took longer than the rest of a 2 s-a-field scan beside the other live tests on
    // two cores (the page then showed the end-of-scan solve).
    let mut run = Run::start(
        &dir.path().join("out"),
        3,
        4.0,
        &[
            "--set",
            "matcher.min_ncc=0.9999",
            "--view",
            "--view-linger-s",
            "60",
        ],
    );
    let url = run.url("live view at ");
    let mid = wait_state(&url, 120, "a weak link mid-scan", |s| {
        let n = s["tiles_registered"].as_u64().unwrap();
        assert!(n < 9, "the scan finished before a weak link showed: {s}");
        s["pairs"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["weak_link"] == true)
    });
    // Mid-scan: the matcher has not finished (no report, no end-of-scan solve).
    assert_eq!(mid["scan_ended"], false);
    assert!(
        !mid["stages"]
            .as_array()
            .unwrap()
            .iter()
            .any(|l| l["stage"] == "matcher"),
        "the matcher's report is not in yet: {mid}"
    );
    let pairs = mid["pairs"].as_array().unwrap();
    for p in pairs {
        assert_eq!(p["final_solve"], false, "streaming records: {p}");
        let ncc = p["ncc"].as_f64().expect("each pair's NCC");
        assert!(ncc < 0.9999, "{p}");
        assert_eq!(p["accepted"], p["weak_link"], "accepted = weak here: {p}");
        if p["accepted"] == false {
            assert!(p["reason"].as_str().unwrap().contains("below"), "{p}");
        }
    }
    let weak = pairs.iter().find(|p| p["weak_link"] == true).unwrap();
    let tiles = mid["tiles"].as_array().unwrap();
    let tile = |i: &serde_json::Value| tiles.iter().find(|t| t["index"] == *i).cloned();
    // The later tile of the weak pair is registered (the pair placed it) and shown amber.
    let b = tile(&weak["b"]).expect("the weak pair's later tile is in the state");
    assert_eq!(b["placement"], "weak_link", "{b}");
    assert_eq!(weak["residual_of"], "streaming_placement", "{weak}");
    assert!(weak["residual_px"]
        .as_f64()
        .is_some_and(|r| r.is_finite() && r >= 0.0));
    // Stage fallbacks show as they happen too.
    assert!(
        tiles.iter().all(|t| t["placement"].is_null()
            || t["placement"] == "weak_link"
            || t["placement"] == "stage_fallback"
            || t["index"] == 0),
        "{mid}"
    );

    // On the page mid-scan: the pairs table and amber boxes.
    let dom = chromium(&url, &dir.path().join("weak.png"));
    assert!(
        dom.matches("data-weak=\"true\"").count() >= 1,
        "a weak pair's row on the page"
    );
    assert!(
        dom.contains("class=\"tile weak_link\""),
        "an amber tile box on the page"
    );
    let note = element_text(&dom, "pairs-note").unwrap();
    assert!(note.starts_with("as the matcher decides them"), "{note}");

    // At the end the report's pairs (the global solve's residuals) replace the streaming ones.
    let fin = wait_state(&url, 300, "the verdict", |s| !s["verdict"].is_null());
    let pairs = fin["pairs"].as_array().unwrap();
    assert!(pairs.iter().all(|p| p["final_solve"] == true), "{fin}");
    assert!(pairs.iter().any(|p| p["weak_link"] == true));
    unsafe {
        libc::kill(run.child.id() as libc::pid_t, libc::SIGINT);
    }
    let (exit, _) = run.wait();
    assert!(exit.success(), "{exit:?}");
}
