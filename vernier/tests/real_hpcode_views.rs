//! Every HP code image of the data set, under the settings a user types (`--hpcode --period
//! 15.5 --code-size W`, nothing else: polarity and window automatic), in its 4 rotations and 2
//! flips, each also re-encoded as JPEG at quality 90 (issue 11): the same markers with the same
//! IDs in every view, and never an ID that is not in the image.

mod common;

use common::RealImage;
use vernier::GreyImage;

/// One real image (file, the IDs of its markers, how many of them every view must give: all,
/// except where a marker is physically damaged, see the notes) and its code size W.
struct Case {
    image: RealImage,
    code_size: usize,
}

/// A [`Case`] of `file` with code size `code_size`.
const fn case(file: &'static str, code_size: usize, ids: &'static [u64], required: usize) -> Case {
    Case {
        image: RealImage {
            file,
            ids,
            required,
        },
        code_size,
    }
}

const CASES: &[Case] = &[
    // Dark dots on a bright background; the period typed (15.5) is not the real one (20).
    case("HPCodeImage_20um.png", 33, &[0, 1], 2),
    case("Image96.png", 33, &[0, 1], 2),
    case("Image100.png", 33, &[0, 1], 2),
    // Dark dots, dust over a finder and the ID row, text beside the marker.
    case("code17.jpg", 37, &[0], 1),
    case("code18.jpg", 37, &[1], 1),
    case("code18_90.jpg", 37, &[1], 1),
    case("code18_180.jpg", 37, &[1], 1),
    case("code19.png", 33, &[0], 1),
    // The second marker's left dot column is cut by the edge of its part: whether it is seen
    // from the front (ID 0) or mirrored cannot be told, so it is dropped, never guessed.
    case("code21.jpg", 33, &[0, 0], 1),
    // Uneven illumination, a hair across the second marker's ID row: one of its ID dots sits
    // halfway between present and missing (ID 0 or 16), so that marker is dropped, never
    // guessed. (A quarter-turn reading of it, ID 0 by luck, passed before the corner check
    // followed the illumination; `the_hidden_id_of_code22_is_not_read_a_quarter_turn`.)
    case("code22.tif", 33, &[0, 0], 1),
    // Table photo, three markers with finders a few pixels wide, dust over the dot fields.
    case("code31.jpg", 37, &[0, 1, 2], 3),
];

/// The six views: identity, three rotations, two flips.
fn views(image: &GreyImage) -> Vec<(&'static str, GreyImage)> {
    let r90 = image.rotated_90_clockwise();
    let r180 = r90.rotated_90_clockwise();
    let r270 = r180.rotated_90_clockwise();
    vec![
        ("r0", image.clone()),
        ("r90", r90),
        ("r180", r180),
        ("r270", r270),
        ("flip-h", image.flipped_horizontally()),
        ("flip-v", image.flipped_vertically()),
    ]
}

#[test]
fn every_view_of_every_hp_code_image_gives_its_markers() {
    let dir = common::data_dir().join("hpcode");
    let mut failures = Vec::new();
    let mut views_checked = 0;
    for case in CASES {
        let mut detector = common::hp_detector(15.5, case.code_size);
        let case = &case.image;
        let image = GreyImage::open(dir.join(case.file)).unwrap();
        for (name, view) in views(&image) {
            for (encoding, view) in [("png", view.clone()), ("jpeg90", common::jpeg(&view, 90))] {
                views_checked += 1;
                let found = detector.detect(&view).unwrap();
                let mut ids: Vec<u64> = found.iter().map(|m| m.id).collect();
                ids.sort_unstable();
                let stray = ids.iter().any(|id| !case.ids.contains(id));
                let confident = found
                    .iter()
                    .all(|m| m.decode_confidence.is_some_and(|c| c >= 0.2));
                if stray || ids.len() < case.required || ids.len() > case.ids.len() || !confident {
                    failures.push(format!(
                        "{} {name} {encoding}: IDs {ids:?}, expected {:?} (at least {})",
                        case.file, case.ids, case.required
                    ));
                }
            }
        }
    }
    assert_eq!(views_checked, CASES.len() * 12);
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// `code22.tif`: the second marker (right, x ≈ 495 px) is the first turned by a quarter turn
/// (its corner finder is bottom-left, the first's bottom-right). Its ID cannot be read (see
/// [`CASES`]); a reading of it, if any, must carry that quarter turn.
#[test]
fn the_hidden_id_of_code22_is_not_read_a_quarter_turn() {
    let image = GreyImage::open(common::data_dir().join("hpcode/code22.tif")).unwrap();
    let found = common::hp_detector(15.5, 33).detect(&image).unwrap();
    let left = found
        .iter()
        .find(|m| m.origin_px.x < 320.0)
        .expect("the left marker is found");
    for m in found.iter().filter(|m| m.origin_px.x >= 320.0) {
        let turn = vernier::phase::wrap_to_pi(m.pose.alpha - left.pose.alpha);
        assert!(
            (turn.abs() - std::f64::consts::FRAC_PI_2).abs() < 0.05,
            "right marker read {turn:.3} rad from the left one"
        );
    }
}

/// `code22.tif`'s second marker, its ID dot half hidden by a hair (ID 0 or 16), is refused, not
/// decided: a sharpened reading would decide it (ID 0 at confidence 0.30), so the marker is read
/// sharpened only when out of focus, which it is not (bridge rise 0.15, against 0.34;
/// docs/design.md#hp-blurred-finders).
#[test]
fn the_hair_crossed_marker_of_code22_is_not_decided_by_sharpening() {
    let image = GreyImage::open(common::data_dir().join("hpcode/code22.tif")).unwrap();
    let found = common::hp_detector(15.5, 33).detect(&image).unwrap();
    let positions: Vec<_> = found.iter().map(|m| (m.id, m.origin_px)).collect();
    assert_eq!(found.len(), 1, "{positions:?}");
    assert!(found[0].origin_px.x < 320.0, "{positions:?}");
}

/// Every HP code image of the data set made worse in the ways a lab makes images worse
/// (issue 11: real dots, real clutter, synthetic degradations): the markers found and the
/// IDs that are not in the image, per degradation, printed as a table. No degradation may give
/// a wrong ID (an occluded or damaged ID dot read as missing once gave another marker's ID);
/// the mild ones must keep every marker.
/// `HPCodeImage_20um.png` in perspective (far edge 5 and 6.5 % narrower): each marker's legs
/// then differ by 8 %, while finders of both markers form a right angle with legs equal within
/// 4 %. That triple, tried first, gives no marker; its finders must go to the next-best
/// triples (both markers were lost before).
#[test]
fn finders_of_a_failed_triple_go_to_the_next_ones() {
    let image = GreyImage::open(common::data_dir().join("hpcode/HPCodeImage_20um.png")).unwrap();
    for fraction in [0.05, 0.065] {
        let seen = common::keystone(&image, fraction);
        let found = common::hp_detector(15.5, 33).detect(&seen).unwrap();
        let mut ids: Vec<u64> = found.iter().map(|m| m.id).collect();
        ids.sort_unstable();
        assert_eq!(ids, [0, 1], "keystone {fraction}");
    }
}

/// `code31.jpg` blurred by 2 px (0.55 module): its printed finders have a grey gap, which the
/// blur lifts over the mid-range of the local range (dark frame to bright centre) while the
/// one-module ring sinks below its upper level, so no level of the local range opens the gap
/// and closes the ring: 5 of the 9 finders were found. The blurred-finder rescue binarises a
/// window around each such centre between its own gap's and ring's levels.
#[test]
fn blurred_finders_with_a_grey_gap_are_found() {
    use vernier::hpcode::{HpCodeDetector, HpCodeParams};
    let image = GreyImage::open(common::data_dir().join("hpcode/code31.jpg")).unwrap();
    let mut detector = HpCodeDetector::new(HpCodeParams::new(15.5, 37)).unwrap();
    let markers = detector.detect(&image).unwrap();
    assert_eq!(markers.len(), 3);
    let blurred = common::blurred(&image, 2.0);
    let finders = detector.find_finders(&blurred);
    let mut seen = 0;
    for marker in &markers {
        let triple = &marker.finders;
        for truth in [triple.corner, triple.right, triple.bottom] {
            seen += usize::from(finders.iter().any(|f| {
                f.polarity == marker.polarity
                    && (f.center - truth).norm() < 1.5
                    && (f.module_px / triple.module_px - 1.0).abs() < 0.15
            }));
        }
    }
    assert!(seen >= 8, "{seen} of the 9 finders found under blur");
}

#[test]
fn real_images_made_worse_never_give_a_wrong_id() {
    let dir = common::data_dir().join("hpcode");
    let images: Vec<(RealImage, GreyImage)> = CASES
        .iter()
        .map(|case| {
            let image = GreyImage::open(dir.join(case.image.file)).unwrap();
            (case.image, image)
        })
        .collect();
    let failures = common::degraded_views(&images, |i, view| {
        let mut detector = common::hp_detector(15.5, CASES[i].code_size);
        detector
            .detect(view)
            .unwrap()
            .iter()
            .map(|m| m.id)
            .collect()
    });
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
