//! The machine at the media scale against the real engine, and the engine's discipline
//! against fake engines.

use std::path::Path;
use std::sync::atomic::AtomicBool;

use surfstream_finish::engine::EngineCommand;
use surfstream_finish::machine::{run_machine, MachineSetting, PartSpec};

/// The scaled machine of the tests: a 15 x 24 mm drum (504 media of 3 mm at 70 % fill) at the
/// paper's 135 mm and 300 / -300 r/min, a 10 x 16 mm aluminium plate.
fn small(seed: u64) -> MachineSetting {
    MachineSetting {
        drum_radius_mm: 15.0,
        drum_height_mm: 24.0,
        part: PartSpec::Plate {
            width_mm: 10.0,
            length_mm: 16.0,
        },
        settle_s: 0.1,
        record_s: 1.0,
        seed,
        ..MachineSetting::default()
    }
}

fn real_engine() -> Option<EngineCommand> {
    match EngineCommand::locate(1, None) {
        Ok(e) => Some(e),
        Err(e) => {
            eprintln!("SKIPPED: the machine tests need the real engine: {e}");
            None
        }
    }
}

fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / (0.5 * (a + b))
}

/// Two seeds (different starting beds) agree on the contact statistics, and a four times
/// stiffer medium (E 1.2e8 Pa, half the time step) on what the record trusts (the bounds and
/// what they were measured at: docs/finish.md, "The machine").
#[test]
fn the_macro_statistics_are_stable_across_seeds_and_softenings() {
    let Some(e) = real_engine() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let stop = AtomicBool::new(false);
    let stiff = {
        let mut s = small(3);
        s.media.youngs_modulus_pa = 1.2e8;
        s
    };
    let runs: Vec<_> = [small(1), small(2), stiff]
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let m = run_machine(s, &tmp.path().join(format!("m{i}")), &e, &stop, &mut |_| {})
                .unwrap();
            let c = &m.contacts;
            eprintln!(
                "seed {} E {:e}: {} media, {} contacts ({} enduring), rate {:.3} /mm^2/s, normal speed p50 {:.5} m/s, \
                 tangential p50 {:.5} m/s, normal force p50 {:.5} N, enduring force p50 {:.5} N, impact speed p50 {:.4} m/s, \
                 sliding work {:.4e} J/mm^2/s, impact energy {:.4e} J/mm^2/s, Coulomb share {:.3}, {} samples; \
                 loop {:.1} s, {:.3e} s per particle-step",
                s.seed, s.media.youngs_modulus_pa, m.media_count, c.count, c.enduring, c.rate_per_mm2_s,
                c.normal_speed_m_s.p50, c.tangential_speed_m_s.p50, c.normal_force_n.p50,
                c.enduring_normal_force_n.p50, c.impact_normal_speed_m_s.p50,
                c.sliding_work_j_per_mm2_s, c.impact_energy_j_per_mm2_s, c.coulomb_limit_share,
                c.samples, m.cost.loop_s, m.cost.per_particle_step_s
            );
            assert_eq!(m.media_lost, 0);
            assert!(!m.partial && m.samples.len() == c.count.min(s.samples_kept));
            assert!((m.simulated_s - s.record_s).abs() < 1e-3);
            m
        })
        .collect();
    let (a, b, c) = (&runs[0].contacts, &runs[1].contacts, &runs[2].contacts);
    assert!(a.count > 100, "too few contacts to compare: {}", a.count);
    let rel = |what: &str, x: f64, y: f64, bound: f64| {
        let r = relative(x, y);
        eprintln!("{what}: {x:.5e} vs {y:.5e}, differ by {r:.3} (bound {bound:.3})");
        assert!(
            r < bound,
            "{what}: {x} vs {y} differ by {r:.3}, bound {bound:.3}"
        );
    };
    // Two seeds: the speeds and the energy fluxes within 10 %, the rate within three
    // standard deviations of the difference of two Poisson counts (about 300 contacts each
    // here: 23 %; the 10 % needs some 2 000 contacts per run).
    let poisson = 3.0 * (1.0 / a.count as f64 + 1.0 / b.count as f64).sqrt();
    rel("seeds: rate", a.rate_per_mm2_s, b.rate_per_mm2_s, poisson);
    rel(
        "seeds: normal speed p50",
        a.normal_speed_m_s.p50,
        b.normal_speed_m_s.p50,
        0.10,
    );
    rel(
        "seeds: tangential speed p50",
        a.tangential_speed_m_s.p50,
        b.tangential_speed_m_s.p50,
        0.15,
    );
    rel(
        "seeds: sliding work",
        a.sliding_work_j_per_mm2_s,
        b.sliding_work_j_per_mm2_s,
        0.10,
    );
    rel(
        "seeds: impact energy",
        a.impact_energy_j_per_mm2_s,
        b.impact_energy_j_per_mm2_s,
        0.10,
    );
    // Four times stiffer: what the record trusts (Softening::trusted) stays; the count of
    // contacts does not (stiffer media chatter: more, shorter contacts), nor the impacts'
    // median approach speed, nor the enduring contacts' load (which contacts count as
    // enduring depends on the Hertz time, hence on E: 14 % and 31 % apart in two runs).
    rel(
        "softenings: tangential speed p50",
        a.tangential_speed_m_s.p50,
        c.tangential_speed_m_s.p50,
        0.20,
    );
    rel(
        "softenings: sliding work",
        a.sliding_work_j_per_mm2_s,
        c.sliding_work_j_per_mm2_s,
        0.20,
    );
    rel(
        "softenings: impact energy",
        a.impact_energy_j_per_mm2_s,
        c.impact_energy_j_per_mm2_s,
        0.10,
    );

    eprintln!(
        "softenings, not trusted: rate {:.3} vs {:.3}, impact speed p50 {:.4} vs {:.4}, enduring force p50 {:.4} vs {:.4} N, duration p50 {:.2e} vs {:.2e} s",
        a.rate_per_mm2_s, c.rate_per_mm2_s, a.impact_normal_speed_m_s.p50, c.impact_normal_speed_m_s.p50,
        a.enduring_normal_force_n.p50, c.enduring_normal_force_n.p50,
        a.duration_s.p50, c.duration_s.p50
    );
}

// ---- The engine's discipline, against fake engines (shell scripts in the engine's place). ----

use std::os::unix::fs::PermissionsExt;
use std::time::{Duration, Instant};

use surfstream_finish::engine::{run_engine_watched, EngineWatch};

/// A fake engine: `body` as a shell script called with `-in IN -log LOG` ($4 is the log).
fn fake_engine(dir: &Path, body: &str) -> EngineCommand {
    let path = dir.join("liggghts");
    std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    std::fs::write(dir.join("in.fake"), "# nothing\n").unwrap();
    EngineCommand {
        liggghts: path,
        ranks: 1,
        hostfile: None,
    }
}

fn run_fake(e: &EngineCommand, dir: &Path, watch: &EngineWatch) -> anyhow::Result<()> {
    let stop = AtomicBool::new(false);
    run_engine_watched(
        e,
        dir,
        "in.fake",
        "log.fake",
        10,
        1,
        &stop,
        &mut |_| {},
        watch,
    )
    .map(|_| ())
}

/// Whether any process of group `pgid` is alive (zombies count as gone).
fn group_alive(pgid: i32) -> bool {
    std::fs::read_dir("/proc").unwrap().flatten().any(|d| {
        let Ok(stat) = std::fs::read_to_string(d.path().join("stat")) else {
            return false;
        };
        // pid (comm) state ppid pgrp ...
        let Some(rest) = stat.rsplit_once(") ").map(|(_, r)| r) else {
            return false;
        };
        let w: Vec<&str> = rest.split_whitespace().collect();
        w.len() > 2 && w[2] == pgid.to_string() && w[0] != "Z"
    })
}

fn wait_until(limit: Duration, what: &str, mut f: impl FnMut() -> bool) {
    let t = Instant::now();
    while !f() {
        assert!(t.elapsed() < limit, "{what} within {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_stalled_engine_is_killed_and_named() {
    let tmp = tempfile::tempdir().unwrap();
    // One thermo line, then the engine stops itself (as SIGSTOP would).
    let e = fake_engine(
        tmp.path(),
        "echo $$ > engine.pid\necho '    1 1 0 0'\nkill -STOP $$\necho never",
    );
    let watch = EngineWatch {
        name: "cycle 3".into(),
        stall_s: 1.5,
    };
    let t = Instant::now();
    let err = run_fake(&e, tmp.path(), &watch).unwrap_err().to_string();
    let took = t.elapsed();
    assert!(err.contains("stalled in cycle 3"), "{err}");
    assert!(err.contains("no output for"), "{err}");
    assert!(took < Duration::from_secs(30), "{took:?}");
    let pid: i32 = std::fs::read_to_string(tmp.path().join("engine.pid"))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(!group_alive(pid), "the stopped engine is still there");
}

#[test]
fn a_failing_engine_names_its_log_and_its_error() {
    let tmp = tempfile::tempdir().unwrap();
    let e = fake_engine(
        tmp.path(),
        "echo 'LIGGGHTS (fake)' > $4\necho 'ERROR: Illegal thermo command (fake)' >> $4\necho 'Last command: thermo' >> $4\nexit 1",
    );
    let watch = EngineWatch {
        name: "cycle 2".into(),
        stall_s: 60.0,
    };
    let err = run_fake(&e, tmp.path(), &watch).unwrap_err().to_string();
    assert!(err.contains("LIGGGHTS failed in cycle 2"), "{err}");
    assert!(err.contains("exit status: 1"), "{err}");
    assert!(
        err.contains("ERROR: Illegal thermo command (fake)"),
        "{err}"
    );
    assert!(
        err.contains(&format!("see {}", tmp.path().join("log.fake").display())),
        "{err}"
    );
    // No log at all: the message says so instead of pointing at a file that is not there.
    let e = fake_engine(tmp.path(), "echo 'segfault (fake)' >&2\nexit 139");
    std::fs::remove_file(tmp.path().join("log.fake")).unwrap();
    let err = run_fake(&e, tmp.path(), &watch).unwrap_err().to_string();
    assert!(err.contains("exit status: 139"), "{err}");
    assert!(err.contains("segfault (fake)"), "{err}");
    assert!(err.contains("no log was written"), "{err}");
    // Exit 0 without running the script: the machine run refuses to summarise nothing.
    let e = fake_engine(tmp.path(), "echo 'LIGGGHTS (fake)' > $4\nexit 0");
    let stop = AtomicBool::new(false);
    let err = run_machine(&small(1), &tmp.path().join("macro"), &e, &stop, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("ended without finishing"), "{err}");
}

/// Helper for the next test: runs a fake engine that never ends, as a parent that the test
/// kills. Does nothing unless the test below started it.
#[test]
#[ignore]
fn helper_parent_of_a_fake_engine() {
    let Ok(dir) = std::env::var("SURFSTREAM_TEST_FAKE_PARENT_DIR") else {
        return;
    };
    let dir = Path::new(&dir);
    let e = EngineCommand {
        liggghts: dir.join("liggghts"),
        ranks: 1,
        hostfile: None,
    };
    let _ = run_fake(&e, dir, &EngineWatch::default());
}

#[test]
fn the_engine_dies_with_its_parent() {
    let tmp = tempfile::tempdir().unwrap();
    fake_engine(
        tmp.path(),
        "echo $$ > engine.pid\nwhile :; do echo '    1 1 0 0'; sleep 0.2; done",
    );
    let mut parent = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "helper_parent_of_a_fake_engine",
            "--ignored",
            "--nocapture",
        ])
        .env("SURFSTREAM_TEST_FAKE_PARENT_DIR", tmp.path())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let pid_file = tmp.path().join("engine.pid");
    wait_until(Duration::from_secs(60), "the fake engine starts", || {
        pid_file.is_file()
    });
    let pid: i32 = std::fs::read_to_string(&pid_file)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!(group_alive(pid));
    parent.kill().unwrap();
    parent.wait().unwrap();
    wait_until(
        Duration::from_secs(10),
        "the engine's process group ends with its parent",
        || !group_alive(pid),
    );
}
