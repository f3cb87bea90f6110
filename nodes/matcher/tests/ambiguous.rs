//! Ambiguous pairs (several equally good NCC maxima, as on periodic textures) resolved by the
//! global solve: the offset consistent with the rest of the tile graph is taken, and a tile
//! whose only evidence is one ambiguous pair stays placed by the stage, never at a wrong peak.

use surfstream_matcher::global::{solve_positions_with_alternatives, AmbiguousLink};
use surfstream_matcher::{Link, SolveParams};

/// A 3 x 3 grid, 200 px steps, true positions = stage + a known error of up to 3 px.
fn grid() -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
    let errors = [
        [0.0, 0.0],
        [2.1, -1.3],
        [-2.7, 0.4],
        [1.2, 2.9],
        [-0.6, -2.2],
        [2.8, 1.7],
        [-1.9, -2.6],
        [0.7, 2.4],
        [-2.3, 1.1],
    ];
    let mut stage = Vec::new();
    let mut truth = Vec::new();
    for r in 0..3 {
        for c in 0..3 {
            let s = [c as f64 * 200.0, r as f64 * 200.0];
            let e = errors[r * 3 + c];
            stage.push(s);
            truth.push([s[0] + e[0], s[1] + e[1]]);
        }
    }
    (stage, truth)
}

fn offset(truth: &[[f64; 2]], a: usize, b: usize) -> [f64; 2] {
    [truth[b][0] - truth[a][0], truth[b][1] - truth[a][1]]
}

/// Every grid-neighbour pair (a, b) with a < b.
fn neighbour_pairs() -> Vec<(usize, usize)> {
    let mut v = Vec::new();
    for r in 0..3 {
        for c in 0..3 {
            let i = r * 3 + c;
            if c + 1 < 3 {
                v.push((i, i + 1));
            }
            if r + 1 < 3 {
                v.push((i, i + 3));
            }
        }
    }
    v
}

/// Positions relative to tile 0, as the scoring does (the one global translation is free).
fn max_error(got: &[[f64; 2]], truth: &[[f64; 2]]) -> f64 {
    let d0 = [got[0][0] - truth[0][0], got[0][1] - truth[0][1]];
    got.iter()
        .zip(truth)
        .map(|(g, t)| (g[0] - t[0] - d0[0]).hypot(g[1] - t[1] - d0[1]))
        .fold(0.0, f64::max)
}

#[test]
fn consistent_alternative_is_chosen_between_placed_tiles_and_for_an_unplaced_tile() {
    let (stage, truth) = grid();
    // Tile 8 (corner) has only ambiguous pairs (5-8 and 7-8); so has pair 3-4 between two
    // tiles placed by other links. Each ambiguous pair offers the true offset and a rival one
    // "period" (6 px) away along the pair's direction (where a lay makes the overlap look
    // alike), listed first half of the time so order cannot decide.
    let ambiguous_pairs = [(5usize, 8usize), (7, 8), (3, 4)];
    let mut links = Vec::new();
    let mut ambiguous = Vec::new();
    for (k, (a, b)) in neighbour_pairs().into_iter().enumerate() {
        let o = offset(&truth, a, b);
        if ambiguous_pairs.contains(&(a, b)) {
            let rival = if b == a + 1 {
                [o[0] + 6.0, o[1] - 0.5]
            } else {
                [o[0] + 0.4, o[1] - 6.0]
            };
            let offsets_px = if k % 2 == 0 {
                vec![rival, o]
            } else {
                vec![o, rival]
            };
            ambiguous.push(AmbiguousLink {
                a,
                b,
                offsets_px,
                sigma_px: 0.05,
            });
        } else {
            links.push(Link {
                a,
                b,
                offset_px: [o[0] + 0.02, o[1] - 0.01],
                sigma_px: 0.05,
            });
        }
    }
    let (sol, chosen) =
        solve_positions_with_alternatives(&stage, &links, &ambiguous, &SolveParams::default())
            .expect("solve");
    for (l, c) in ambiguous.iter().zip(&chosen) {
        let c = c.unwrap_or_else(|| panic!("pair {}-{} left unresolved", l.a, l.b));
        let o = offset(&truth, l.a, l.b);
        let got = l.offsets_px[c];
        assert!(
            (got[0] - o[0]).hypot(got[1] - o[1]) < 0.1,
            "pair {}-{}: chose {got:?}, truth {o:?}",
            l.a,
            l.b
        );
    }
    assert!(sol.linked.iter().all(|&l| l), "every tile placed by links");
    let e = max_error(&sol.positions_px, &truth);
    assert!(e < 0.1, "max position error {e} px");
}

#[test]
fn single_ambiguous_pair_leaves_the_tile_to_the_stage() {
    let (stage, truth) = grid();
    // Tile 8's pairs: 5-8 refused outright (no link), 7-8 ambiguous. One ambiguous pair gives
    // two equally supported positions: no honest choice, so none is made.
    let mut links = Vec::new();
    let mut ambiguous = Vec::new();
    for (a, b) in neighbour_pairs() {
        let o = offset(&truth, a, b);
        match (a, b) {
            (5, 8) => {}
            (7, 8) => ambiguous.push(AmbiguousLink {
                a,
                b,
                offsets_px: vec![[o[0] - 5.0, o[1] + 0.3], o],
                sigma_px: 0.05,
            }),
            _ => links.push(Link {
                a,
                b,
                offset_px: o,
                sigma_px: 0.05,
            }),
        }
    }
    let (sol, chosen) =
        solve_positions_with_alternatives(&stage, &links, &ambiguous, &SolveParams::default())
            .expect("solve");
    assert_eq!(chosen, vec![None]);
    assert!(!sol.linked[8], "tile 8 must be left to the stage");
    assert!(sol.linked[..8].iter().all(|&l| l));
}

#[test]
fn two_distinct_agreeing_positions_are_refused() {
    let (stage, truth) = grid();
    // Both of tile 8's pairs offer the same two positions (a texture periodic along the whole
    // scan): two positions have the support of two pairs, so neither is taken.
    let mut links = Vec::new();
    let mut ambiguous = Vec::new();
    for (a, b) in neighbour_pairs() {
        let o = offset(&truth, a, b);
        if b == 8 {
            ambiguous.push(AmbiguousLink {
                a,
                b,
                offsets_px: vec![o, [o[0] + 7.0, o[1]]],
                sigma_px: 0.05,
            });
        } else {
            links.push(Link {
                a,
                b,
                offset_px: o,
                sigma_px: 0.05,
            });
        }
    }
    let (sol, chosen) =
        solve_positions_with_alternatives(&stage, &links, &ambiguous, &SolveParams::default())
            .expect("solve");
    assert_eq!(chosen, vec![None, None]);
    assert!(!sol.linked[8]);
}

#[test]
fn malformed_ambiguous_links_are_errors() {
    let (stage, _) = grid();
    let params = SolveParams::default();
    let bad_tile = AmbiguousLink {
        a: 0,
        b: 9,
        offsets_px: vec![[200.0, 0.0]],
        sigma_px: 0.05,
    };
    let e = solve_positions_with_alternatives(&stage, &[], &[bad_tile], &params).unwrap_err();
    assert!(e.to_string().contains("tile index 9"), "{e}");
    let bad_offset = AmbiguousLink {
        a: 0,
        b: 1,
        offsets_px: vec![[f64::NAN, 0.0]],
        sigma_px: 0.05,
    };
    let e = solve_positions_with_alternatives(&stage, &[], &[bad_offset], &params).unwrap_err();
    assert!(e.to_string().contains("not finite"), "{e}");
    let self_link = AmbiguousLink {
        a: 2,
        b: 2,
        offsets_px: vec![[0.0, 0.0]],
        sigma_px: 0.05,
    };
    let e = solve_positions_with_alternatives(&stage, &[], &[self_link], &params).unwrap_err();
    assert!(e.to_string().contains("to itself"), "{e}");
}
