//! One binary, three roles, each its own process:
//!
//!   tunnel-bench tunnel ROOT listen|connect ENDPOINT     a tunnel for the iceoryx2 root ROOT
//!   tunnel-bench pub ROOT FRAMES BYTES INTERVAL_MS        frames into the root ROOT
//!   tunnel-bench sub ROOT FRAMES                          frames out of the root ROOT
//!
//! A root is an iceoryx2 prefix: services made under one are invisible under another, as on
//! two hosts. Each frame carries its sequence number and the publisher's wall clock in its
//! first 16 bytes, so the subscriber measures latency (one machine, one clock) and loss.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, bail, Result};
use iceoryx2::prelude::*;
use iceoryx2::service::ipc::Service as Ipc;
use iceoryx2_tunnel::Tunnel;
use iceoryx2_tunnel_zenoh::ZenohBackend;

const SERVICE: &str = "surfstream/bench/panorama";

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize| {
        args.get(i)
            .cloned()
            .ok_or_else(|| anyhow!("missing argument {i}: see src/main.rs for the usage"))
    };
    match arg(1)?.as_str() {
        "tunnel" => tunnel(&arg(2)?, &arg(3)?, &arg(4)?),
        "pub" => publish(
            &arg(2)?,
            arg(3)?.parse()?,
            arg(4)?.parse()?,
            arg(5)?.parse()?,
        ),
        "sub" => subscribe(&arg(2)?, arg(3)?.parse()?),
        other => bail!("unknown role {other}"),
    }
}

fn root_config(root: &str) -> Result<Config> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(format!("{root}_").as_bytes())
        .map_err(|e| anyhow!("bad root name {root}: {e:?}"))?;
    Ok(config)
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

fn tunnel(root: &str, how: &str, endpoint: &str) -> Result<()> {
    let mut zenoh_config = zenoh::Config::default();
    let key = match how {
        "listen" => "listen/endpoints",
        "connect" => "connect/endpoints",
        other => bail!("tunnel: expected listen or connect, got {other}"),
    };
    zenoh_config
        .insert_json5(key, &format!("[\"{endpoint}\"]"))
        .map_err(|e| anyhow!("zenoh config: {e}"))?;
    zenoh_config
        .insert_json5("scouting/multicast/enabled", "false")
        .map_err(|e| anyhow!("zenoh config: {e}"))?;
    let mut tunnel = Tunnel::<Ipc, ZenohBackend<Ipc>>::create(
        &iceoryx2_tunnel::Config::default(),
        &root_config(root)?,
        &zenoh_config,
    )
    .map_err(|e| anyhow!("tunnel {root}: {e:?}"))?;
    eprintln!("tunnel {root}: up ({how} {endpoint})");
    loop {
        tunnel
            .discover()
            .map_err(|e| anyhow!("tunnel {root}: discover: {e:?}"))?;
        tunnel
            .propagate()
            .map_err(|e| anyhow!("tunnel {root}: propagate: {e:?}"))?;
        std::thread::sleep(Duration::from_micros(200));
    }
}

fn node(root: &str) -> Result<Node<Ipc>> {
    NodeBuilder::new()
        .config(&root_config(root)?)
        .create::<Ipc>()
        .map_err(|e| anyhow!("node in {root}: {e:?}"))
}

fn publish(root: &str, frames: u64, bytes: usize, interval_ms: u64) -> Result<()> {
    let node = node(root)?;
    let service = node
        .service_builder(&SERVICE.try_into().map_err(|e| anyhow!("{e:?}"))?)
        .publish_subscribe::<[u8]>()
        .history_size(0)
        .subscriber_max_buffer_size(8)
        .open_or_create()
        .map_err(|e| anyhow!("service: {e:?}"))?;
    let publisher = service
        .publisher_builder()
        .initial_max_slice_len(bytes)
        .create()
        .map_err(|e| anyhow!("publisher: {e:?}"))?;
    // Give the tunnels time to discover the service and the remote subscriber.
    std::thread::sleep(Duration::from_secs(3));
    let t0 = Instant::now();
    for seq in 0..frames {
        let sample = publisher
            .loan_slice_uninit(bytes)
            .map_err(|e| anyhow!("loan: {e:?}"))?;
        let stamp = now_ns();
        let sample = sample.write_from_fn(|i| match i {
            0..=7 => seq.to_le_bytes()[i],
            8..=15 => stamp.to_le_bytes()[i - 8],
            _ => (i % 251) as u8,
        });
        sample.send().map_err(|e| anyhow!("send: {e:?}"))?;
        std::thread::sleep(Duration::from_millis(interval_ms));
    }
    eprintln!(
        "pub {root}: {frames} frames of {bytes} B in {:.2} s",
        t0.elapsed().as_secs_f64()
    );
    std::thread::sleep(Duration::from_secs(2));
    Ok(())
}

fn subscribe(root: &str, frames: u64) -> Result<()> {
    let node = node(root)?;
    let deadline = Instant::now() + Duration::from_secs(60);
    // The tunnel creates the service in this root once it has discovered the remote one.
    let service = loop {
        match node
            .service_builder(&SERVICE.try_into().map_err(|e| anyhow!("{e:?}"))?)
            .publish_subscribe::<[u8]>()
            .open()
        {
            Ok(s) => break s,
            Err(_) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(50)),
            Err(e) => bail!("sub {root}: service never appeared: {e:?}"),
        }
    };
    let subscriber = service
        .subscriber_builder()
        .create()
        .map_err(|e| anyhow!("subscriber: {e:?}"))?;
    let mut latencies_ms = Vec::new();
    let (mut bytes, mut next, mut lost, mut corrupt) = (0usize, Some(0u64), 0u64, 0u64);
    let (mut first, mut last): (Option<Instant>, Option<Instant>) = (None, None);
    // Stop at the last sequence number, or 5 s after the last frame (a lost tail).
    let idle = Duration::from_secs(5);
    while next != Some(frames)
        && Instant::now() < deadline
        && last.is_none_or(|l| l.elapsed() < idle)
    {
        match subscriber
            .receive()
            .map_err(|e| anyhow!("receive: {e:?}"))?
        {
            Some(sample) => {
                let now = now_ns();
                let p = sample.payload();
                let word = |o: usize| {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(&p[o..o + 8]);
                    u64::from_le_bytes(b)
                };
                let (seq, stamp) = (word(0), word(8));
                if p.iter()
                    .enumerate()
                    .skip(16)
                    .any(|(i, &v)| v != (i % 251) as u8)
                {
                    corrupt += 1;
                }
                if let Some(n) = next {
                    lost += seq.saturating_sub(n);
                }
                next = Some(seq + 1);
                first.get_or_insert_with(Instant::now);
                last = Some(Instant::now());
                bytes += p.len();
                latencies_ms.push(now.saturating_sub(stamp) as f64 / 1e6);
            }
            None => std::thread::sleep(Duration::from_micros(100)),
        }
    }
    // Frames never seen at the end count as lost too.
    lost += frames.saturating_sub(next.unwrap_or(frames));
    let span = match (first, last) {
        (Some(f), Some(l)) => (l - f).as_secs_f64(),
        _ => 0.0,
    };
    latencies_ms.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        latencies_ms
            .get(((latencies_ms.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "{{\"root\": \"{root}\", \"frames\": {}, \"bytes\": {bytes}, \"lost\": {lost}, \"corrupt\": {corrupt}, \"latency_ms\": {{\"p50\": {:.2}, \"p95\": {:.2}, \"max\": {:.2}}}, \"mb_per_s\": {:.1}}}",
        latencies_ms.len(),
        pct(0.5),
        pct(0.95),
        pct(1.0),
        // Between the first and the last arrival: (n - 1) frames' worth of bytes.
        if span > 0.0 && !latencies_ms.is_empty() {
            bytes as f64 * (latencies_ms.len() as f64 - 1.0) / latencies_ms.len() as f64 / span / 1e6
        } else {
            0.0
        }
    );
    Ok(())
}
