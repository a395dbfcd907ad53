//! Fuzz harnesses of the node's inputs on stable Rust (proptest): parameter files, `-p`
//! values, the ROS argument parser, and CDR decoding of every message type the node takes in
//! (`sensor_msgs/Image` and the `rcl_interfaces` parameter-service requests), each followed by
//! the code that uses the decoded value. Nothing may panic.
//!
//! `cargo test` runs each for a fixed number of cases with a fixed seed; a longer run of all
//! harnesses: `bash scripts/fuzz_long.sh [CASES] [SEED]`.

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestRng, TestRunner};
use ros2_client::rcl_interfaces::{
    GetParametersRequest, ListParametersRequest, SetParametersRequest,
};

fn cdr<T: serde::Serialize>(value: &T) -> Vec<u8> {
    vernier_interface::cdr::body_to_cdr(value).unwrap_or_default()
}

fn from_cdr<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Option<T> {
    vernier_interface::cdr::body_from_cdr(bytes).ok()
}
use crate::messages::{Header, Image};
use crate::param_services::{self, MemoryStore};
use crate::params::NodeParams;
use crate::processing::Processor;
use crate::ros_args::{parse_params_file, RosArgs};

fn runner(default_cases: u32) -> TestRunner {
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<u64>().ok());
    let cases = env("VERNIER_FUZZ_CASES").map_or(default_cases, |c| c as u32);
    let seed = env("VERNIER_FUZZ_SEED").unwrap_or(16);
    let mut bytes = [0u8; 32];
    bytes[..8].copy_from_slice(&seed.to_le_bytes());
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(config, TestRng::from_seed(RngAlgorithm::ChaCha, &bytes))
}

fn no_panic(what: &str, f: impl FnOnce()) -> Result<(), TestCaseError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        .map_err(|_| TestCaseError::fail(format!("{what} panicked")))
}

/// Inserts `tokens[i]` at `at` (a char boundary) for each edit.
fn mutate(text: &str, edits: &[(u16, usize)], tokens: &[&str]) -> String {
    let mut out = text.to_string();
    for &(at, token) in edits {
        let mut i = at as usize % (out.len() + 1);
        while !out.is_char_boundary(i) {
            i -= 1;
        }
        out.insert_str(i, tokens[token % tokens.len()]);
    }
    out
}

const YAML_TOKENS: &[&str] = &[
    "\n",
    "  ",
    ": ",
    "- ",
    "[",
    "]",
    "{",
    "}",
    "&a ",
    "*a",
    "!!str ",
    "1e308",
    "-1",
    "0",
    "5e-324",
    "nan",
    ".inf",
    "'x'",
    "\"",
    "period",
    "code_size",
    "window_size",
    "4294967295",
    "~",
    "#",
    "ros__parameters:",
    "/**:",
    "? ",
    "|\n",
    ">\n",
];

#[test]
fn fuzz_parameter_files() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("params/detector.yaml");
    let seed = std::fs::read_to_string(path).unwrap_or_default();
    let strategy = (
        proptest::collection::vec((any::<u16>(), any::<usize>()), 0..8),
        "\\PC{0,60}",
    );
    runner(200)
        .run(&strategy, |(edits, noise)| {
            let text = mutate(&seed, &edits, YAML_TOKENS);
            no_panic("parameter file", || {
                for text in [&text, &noise] {
                    if let Ok(values) = parse_params_file(text, "/", "vernier_detector") {
                        let _ = NodeParams::from_overrides(&values);
                    }
                }
            })
        })
        .unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn fuzz_ros_arguments() {
    let words = [
        "--ros-args",
        "-p",
        "-r",
        "--params-file",
        "--log-level",
        "--",
        "-e",
        "period:=4",
        "period:=[1,",
        "marker_ids:=[1,2]",
        "a:b:=c",
        ":=",
        "__ns:=/x",
        "__node:=n",
        "x:=",
        "debug",
        "name:=info",
        "--enable-rosout-logs",
        "relative_pairs:=['1:2']",
        "{",
    ];
    let strategy = proptest::collection::vec(
        prop_oneof![
            (0..words.len()).prop_map(move |i| words[i].to_string()),
            "\\PC{0,12}",
        ],
        0..10,
    );
    runner(300)
        .run(&strategy, |args| {
            no_panic("ROS arguments", || {
                if let Ok(parsed) = RosArgs::parse(args.clone()) {
                    if let Ok(values) = parsed.parameter_overrides("/", "vernier_detector") {
                        let _ = NodeParams::from_overrides(&values);
                    }
                    let _ = parsed.resolve_topic("image", "/", "vernier_detector");
                }
            })
        })
        .unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn fuzz_cdr_messages() {
    let image = Image {
        header: Header {
            frame_id: "cam".into(),
            ..Default::default()
        },
        height: 4,
        width: 6,
        encoding: "mono16".into(),
        is_bigendian: 0,
        step: 12,
        data: (0..48).collect(),
    };
    let seeds = [
        cdr(&image),
        cdr(&GetParametersRequest {
            names: vec!["period".into(), "window_size".into()],
        }),
        cdr(&ListParametersRequest {
            prefixes: vec!["a".into()],
            depth: 2,
        }),
    ];
    let store = MemoryStore::with_period();
    let params = store
        .0
        .lock()
        .map(|p| p.clone())
        .unwrap_or_else(|e| panic!("{e}"));
    let mut processor = Processor::new(params, 0).unwrap_or_else(|e| panic!("{e}"));
    let strategy = (
        0..seeds.len(),
        proptest::collection::vec((any::<u16>(), any::<u8>()), 0..12),
        proptest::collection::vec(any::<u8>(), 0..96),
    );
    let processor = std::cell::RefCell::new(&mut processor);
    runner(400)
        .run(&strategy, |(which, flips, raw)| {
            let mut bytes = seeds[which].clone();
            for (at, value) in flips {
                let i = at as usize % bytes.len();
                bytes[i] = value;
            }
            no_panic("CDR decoding", || {
                for bytes in [&bytes, &raw] {
                    if let Some(msg) = from_cdr::<Image>(bytes) {
                        let _ = processor.borrow_mut().process(&msg);
                    }
                    if let Some(req) = from_cdr::<GetParametersRequest>(bytes) {
                        let _ = param_services::get_parameters(&store, &req);
                        let _ = param_services::get_parameter_types(
                            &store,
                            &ros2_client::rcl_interfaces::GetParameterTypesRequest {
                                names: req.names,
                            },
                        );
                    }
                    if let Some(req) = from_cdr::<ListParametersRequest>(bytes) {
                        let _ = param_services::list_parameters(&store, &req);
                    }
                    if let Some(req) = from_cdr::<SetParametersRequest>(bytes) {
                        let _ = param_services::set_parameters(&store, &req);
                        let _ = param_services::set_parameters_atomically(&store, &req);
                    }
                }
            })
        })
        .unwrap_or_else(|e| panic!("{e}"));
}
