//! `vernier bag`: replays the images of a rosbag2 MCAP recording through the detector, with
//! the ROS node's parameter file, and writes the poses back as MCAP (the node's topics and
//! message types) or as a pose table (CSV / JSON Lines).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use vernier_interface::cdr::{from_cdr, to_cdr};
use vernier_interface::messages::{Image, RosType};
use vernier_interface::params::{NodeParams, ParamValue};
use vernier_interface::processing::{FrameOutput, Processor};
use vernier_interface::{ros_args, schemas};

use crate::batch::progress_bar;
use crate::inputs::natural_cmp;
use crate::pose_table::{PoseRow, TableFormat, TableWriter};

/// The message type `vernier bag` reads.
const IMAGE_TYPE: &str = "sensor_msgs/msg/Image";

/// Arguments of `vernier bag`.
#[derive(Parser)]
pub struct BagArgs {
    /// rosbag2 recording: an `.mcap` file, or a rosbag2 folder (its `.mcap` files in order).
    #[arg(long)]
    input: PathBuf,
    /// Image topic (sensor_msgs/msg/Image: mono8, mono16, rgb8, bgr8, rgba8, bgra8).
    #[arg(long, default_value = "/camera/image_raw")]
    topic: String,
    /// ROS parameter file of the detector node (params/detector.yaml); default: the node's
    /// defaults.
    #[arg(long)]
    params: Option<PathBuf>,
    /// JSON pattern file; overrides the parameter file's `pattern_file`.
    #[arg(long)]
    pattern: Option<PathBuf>,
    /// Physical period (in `period_unit`, µm by default); overrides the parameter file.
    #[arg(long)]
    period: Option<f64>,
    /// Output: `.mcap` (geometry_msgs/PoseStamped on `<namespace>/marker_<id>/pose` and
    /// vernier_ros/MarkerPoseArray on `<namespace>/markers`, SI units, as the node
    /// publishes them), or a pose table `.csv` / `.jsonl` (pattern units, like `detect`).
    #[arg(long)]
    output: PathBuf,
    /// Namespace of the output topics (the node's name).
    #[arg(long, default_value = "/vernier_detector")]
    namespace: String,
    /// Exit non-zero when any frame was skipped (undecodable message, bad image, failed
    /// detection, corrupted chunk). Without it, bad frames are skipped, counted and reported
    /// on stderr, and the exit code is 0.
    #[arg(long)]
    strict: bool,
    /// Largest image processed, pixels (`100M`, `4000000`); larger frames are skipped.
    /// Default: the parameter file's `max_image_pixels`, else 100M.
    #[arg(long, value_parser = vernier::limits::parse_pixel_count)]
    max_pixels: Option<u64>,
}

/// The MCAP files of a recording, in order.
fn bag_files(input: &Path) -> Result<Vec<PathBuf>, String> {
    if !input.is_dir() {
        return match input.extension().and_then(|e| e.to_str()) {
            Some("mcap") => Ok(vec![input.to_path_buf()]),
            _ => Err(format!(
                "{}: expected an .mcap file or a rosbag2 folder",
                input.display()
            )),
        };
    }
    let listed: Vec<PathBuf> = std::fs::read_dir(input)
        .map_err(|e| format!("{}: {e}", input.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    let with_ext = |ext: &str| -> Vec<PathBuf> {
        listed
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == ext))
            .cloned()
            .collect()
    };
    let mut files = with_ext("mcap");
    if files.is_empty() {
        let hint = if with_ext("db3").is_empty() {
            ""
        } else {
            " (SQLite .db3 storage is not supported: record with `--storage mcap` or convert \
             with `ros2 bag convert`)"
        };
        return Err(format!("{}: no .mcap file{hint}", input.display()));
    }
    files.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
    Ok(files)
}

/// Where the results go.
enum Sink {
    Mcap(Box<McapSink>),
    Table(TableWriter<BufWriter<File>>),
}

/// MCAP output: the node's topics, schemas in `ros2msg`, CDR payloads.
struct McapSink {
    writer: mcap::Writer<BufWriter<File>>,
    namespace: String,
    /// Schema IDs by ROS type name.
    schemas: BTreeMap<String, u16>,
    /// Channel IDs by topic.
    channels: BTreeMap<String, u16>,
    sequences: BTreeMap<u16, u32>,
}

impl McapSink {
    fn create(path: &Path, namespace: &str) -> Result<Self, String> {
        let file = File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .create(BufWriter::new(file))
            .map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(McapSink {
            writer,
            namespace: namespace.trim_end_matches('/').to_string(),
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            sequences: BTreeMap::new(),
        })
    }

    /// Writes `message` on `<namespace>/<topic>`, creating its schema and channel on first use.
    fn write<T: RosType>(
        &mut self,
        topic: &str,
        schema: fn() -> String,
        time_ns: u64,
        message: &T,
    ) -> Result<(), String> {
        let failed = |e: mcap::McapError| format!("cannot write the output: {e}");
        let type_name = T::ros_name();
        let schema_id = match self.schemas.get(&type_name) {
            Some(&id) => id,
            None => {
                let id = self
                    .writer
                    .add_schema(&type_name, "ros2msg", schema().as_bytes())
                    .map_err(failed)?;
                self.schemas.insert(type_name, id);
                id
            }
        };
        let topic = format!("{}/{topic}", self.namespace);
        let channel = match self.channels.get(&topic) {
            Some(&c) => c,
            None => {
                let c = self
                    .writer
                    .add_channel(schema_id, &topic, "cdr", &BTreeMap::new())
                    .map_err(failed)?;
                self.channels.insert(topic, c);
                c
            }
        };
        let sequence = self.sequences.entry(channel).or_insert(0);
        *sequence += 1;
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: *sequence,
            log_time: time_ns,
            publish_time: time_ns,
        };
        self.writer
            .write_to_known_channel(&header, &to_cdr(message)?)
            .map_err(failed)
    }

    /// The topics the node publishes for one frame (all but /tf and the debug image).
    fn frame(&mut self, time_ns: u64, out: &FrameOutput) -> Result<(), String> {
        self.write("markers", schemas::marker_pose_array, time_ns, &out.markers)?;
        self.write(
            "detections",
            schemas::detection_3d_array,
            time_ns,
            &out.detections,
        )?;
        for (id, pose) in &out.poses {
            self.write(
                &format!("marker_{id}/pose"),
                schemas::pose_stamped,
                time_ns,
                pose,
            )?;
        }
        for (id, pose) in &out.poses_with_covariance {
            let topic = format!("marker_{id}/pose_with_covariance");
            self.write(&topic, schemas::pose_with_covariance_stamped, time_ns, pose)?;
        }
        for ((a, b), pose) in &out.relative {
            let topic = format!("relative/marker_{a}_{b}/pose");
            self.write(&topic, schemas::pose_stamped, time_ns, pose)?;
        }
        Ok(())
    }

    fn finish(mut self) -> Result<(), String> {
        self.writer
            .finish()
            .map_err(|e| format!("cannot finish the output: {e}"))?;
        // Flush and sync with the errors checked (dropping the writer would lose them).
        let file = self
            .writer
            .into_inner()
            .into_inner()
            .map_err(|e| format!("cannot write the output: {}", e.error()))?;
        vernier::output::sync(&file).map_err(|e| format!("cannot write the output: {e}"))
    }
}

/// The node's frame processing and the sink of a replay.
struct Replay {
    processor: Processor,
    sink: Sink,
    frame: u64,
    failures: usize,
}

impl Replay {
    /// Processes one image message (`time_ns`: its log time), exactly as the node does.
    fn image(&mut self, topic: &str, time_ns: u64, payload: &[u8]) -> Result<(), String> {
        let start = Instant::now();
        let msg: Result<Image, String> = from_cdr(payload);
        let result = msg
            .as_ref()
            .map_err(Clone::clone)
            .and_then(|msg| self.processor.process(msg).map_err(|e| e.0));
        let time_ms = start.elapsed().as_secs_f64() * 1e3;
        let failure = match &result {
            Err(e) => Some(e.clone()),
            Ok(out) => out.detect_error.clone(),
        };
        if let Some(e) = &failure {
            eprintln!("vernier: {topic} message {}: skipped: {e}", self.frame);
            self.failures += 1;
        }
        match &mut self.sink {
            Sink::Table(table) => {
                let stamp = msg.as_ref().ok().map(|m| m.header.stamp.as_secs_f64());
                let markers = match (&result, failure) {
                    (Ok(out), None) => Ok(out.raw.clone()),
                    (_, Some(e)) => Err(e),
                    (Err(e), None) => Err(e.clone()),
                };
                let period = self.processor.period();
                let rows =
                    PoseRow::from_result(self.frame, stamp, topic, &markers, time_ms, period);
                table
                    .write(&rows)
                    .map_err(|e| format!("cannot write the output: {e}"))?;
            }
            Sink::Mcap(sink) => {
                // A bad message still gets an (empty) array, as the node publishes on loss.
                let empty;
                let out = match &result {
                    Ok(out) => out,
                    Err(_) => {
                        empty = FrameOutput::default();
                        &empty
                    }
                };
                sink.frame(time_ns, out)?;
            }
        }
        self.frame += 1;
        Ok(())
    }
}

/// The node's parameters for a replay: the parameter file's entries for the node
/// `fq_node` (the node's rules: name patterns, validation, foreign names ignored with a
/// warning), then the command-line overrides.
fn replay_params(args: &BagArgs) -> Result<NodeParams, String> {
    // The parameter file is read as the node reads its `--params-file`.
    let fq_node = args.namespace.trim_end_matches('/');
    let (namespace, node) = match fq_node.rsplit_once('/') {
        Some(("", node)) => ("/", node),
        Some((namespace, node)) => (namespace, node),
        None => ("/", fq_node),
    };
    let file_args = ros_args::RosArgs {
        params_files: args.params.iter().cloned().collect(),
        ..ros_args::RosArgs::default()
    };
    let mut overrides = file_args
        .parameter_overrides(namespace, node)
        .map_err(|e| e.to_string())?;
    if let Some(p) = &args.pattern {
        let text = p.to_string_lossy().into_owned();
        overrides.push(("pattern_file".into(), ParamValue::String(text)));
    }
    if let Some(p) = args.period {
        overrides.push(("period".into(), ParamValue::Double(p)));
    }
    if let Some(p) = args.max_pixels {
        let p = i64::try_from(p).map_err(|_| format!("--max-pixels {p} is too large"))?;
        overrides.push(("max_image_pixels".into(), ParamValue::Integer(p)));
    }
    let startup = NodeParams::from_overrides(&overrides).map_err(|e| match &args.params {
        Some(path) => format!("{}: {e}", path.display()),
        None => e,
    })?;
    for ignored in &startup.ignored {
        eprintln!("vernier: parameter ignored: {ignored}");
    }
    Ok(startup.params)
}

/// Runs `vernier bag`.
pub fn run(args: &BagArgs) -> Result<ExitCode, String> {
    let files = bag_files(&args.input)?;
    let processor = Processor::new(replay_params(args)?, 0)?;
    let sink = open_sink(args)?;
    let mut replay = Replay {
        processor,
        sink,
        frame: 0,
        failures: 0,
    };
    let mut corrupt = 0usize;
    for file in &files {
        corrupt += replay_file(&mut replay, file, args)?;
    }
    if replay.frame == 0 && corrupt == 0 {
        return Err(format!(
            "{}: no message on topic {}",
            args.input.display(),
            args.topic
        ));
    }
    match replay.sink {
        Sink::Mcap(sink) => sink.finish()?,
        Sink::Table(table) => table
            .finish()
            .map_err(|e| format!("cannot write the output: {e}"))?,
    }
    let skipped = replay.failures + corrupt;
    if skipped > 0 {
        eprintln!(
            "vernier: {} of {} frames skipped{}",
            replay.failures,
            replay.frame,
            if corrupt > 0 {
                format!(", and {corrupt} damaged part(s) of the recording")
            } else {
                String::new()
            }
        );
    }
    Ok(if skipped > 0 && args.strict {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// The output the replay writes to, chosen by the `--output` file's extension.
fn open_sink(args: &BagArgs) -> Result<Sink, String> {
    let out = &args.output;
    let sink = match out.extension().and_then(|e| e.to_str()) {
        Some("mcap") => Sink::Mcap(Box::new(McapSink::create(out, &args.namespace)?)),
        Some(ext @ ("csv" | "jsonl" | "json")) => {
            let format = if ext == "csv" {
                TableFormat::Csv
            } else {
                TableFormat::Jsonl
            };
            let file = File::create(out).map_err(|e| format!("{}: {e}", out.display()))?;
            Sink::Table(
                TableWriter::new(BufWriter::new(file), format)
                    .map_err(|e| format!("{}: {e}", out.display()))?,
            )
        }
        _ => {
            return Err(format!(
                "--output `{}`: expected a .mcap, .csv or .jsonl file",
                out.display()
            ))
        }
    };
    Ok(sink)
}

/// Replays the recording `file` (topic `args.topic`) into `replay`; returns the number of
/// damaged parts skipped.
fn replay_file(replay: &mut Replay, file: &Path, args: &BagArgs) -> Result<usize, String> {
    let data = std::fs::read(file).map_err(|e| format!("{}: {e}", file.display()))?;
    let summary = mcap::Summary::read(&data).ok().flatten();
    let total = summary
        .as_ref()
        .map(|s| {
            s.channels
                .values()
                .filter(|c| c.topic == args.topic)
                .filter_map(|c| s.stats.as_ref()?.channel_message_counts.get(&c.id))
                .sum::<u64>()
        })
        .unwrap_or(0);
    let progress = progress_bar(total, "frames");
    let mut handle = |message: &mcap::Message| -> Result<(), String> {
        let channel = &message.channel;
        if channel.topic != args.topic {
            return Ok(());
        }
        let schema = channel.schema.as_ref().map(|s| s.name.as_str());
        if schema.is_some_and(|s| s != IMAGE_TYPE) || channel.message_encoding != "cdr" {
            return Err(format!(
                "{}: topic {} carries {} ({}), expected {IMAGE_TYPE} (cdr)",
                file.display(),
                args.topic,
                schema.unwrap_or("no schema"),
                channel.message_encoding
            ));
        }
        progress.suspend(|| replay.image(&args.topic, message.log_time, &message.data))?;
        progress.inc(1);
        Ok(())
    };
    let report =
        |what: String| progress.suspend(|| eprintln!("vernier: {}: {what}", file.display()));
    let corrupt = match summary.as_ref().filter(|s| !s.chunk_indexes.is_empty()) {
        // Indexed file: chunk by chunk, so a damaged chunk costs only its own frames.
        Some(summary) => replay_chunks(&data, summary, &mut handle, &report)?,
        None => replay_linear(&data, &mut handle, &report)?,
    };
    progress.finish_and_clear();
    Ok(corrupt)
}

/// Replays every chunk of an indexed MCAP file in file order. Each chunk is decoded whole and
/// its CRC checked before any of its messages is used, so corrupted bytes never reach the
/// detector; a damaged chunk is reported and skipped. Returns the number of damaged chunks.
fn replay_chunks(
    data: &[u8],
    summary: &mcap::Summary,
    handle: &mut dyn FnMut(&mcap::Message) -> Result<(), String>,
    report: &dyn Fn(String),
) -> Result<usize, String> {
    let mut chunks: Vec<&mcap::records::ChunkIndex> = summary.chunk_indexes.iter().collect();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    let mut damaged = 0;
    for (k, index) in chunks.iter().enumerate() {
        let messages: mcap::McapResult<Vec<mcap::Message>> = summary
            .stream_chunk(data, index)
            .and_then(|messages| messages.collect());
        match messages {
            Ok(messages) => {
                for message in &messages {
                    handle(message)?;
                }
            }
            Err(e) => {
                report(format!(
                    "chunk {} of {} is damaged, its frames are skipped: {e}",
                    k + 1,
                    chunks.len()
                ));
                damaged += 1;
            }
        }
    }
    Ok(damaged)
}

/// Replays an MCAP file without a usable index, record by record, chunk CRCs checked before a
/// chunk's messages are used. The reader cannot resume after a damaged record, so the rest of
/// the file is reported and skipped. Returns 1 if that happened, else 0.
fn replay_linear(
    data: &[u8],
    handle: &mut dyn FnMut(&mcap::Message) -> Result<(), String>,
    report: &dyn Fn(String),
) -> Result<usize, String> {
    let options = mcap::sans_io::LinearReaderOptions::default()
        .with_prevalidate_chunk_crcs(true)
        .with_validate_data_section_crc(true);
    let mut reader = mcap::sans_io::MessageReader::new_with_options(options);
    let mut rest: &[u8] = data;
    let mut messages = 0usize;
    while let Some(event) = reader.next_event() {
        match event {
            Ok(mcap::sans_io::MessageReadEvent::ReadRequest(need)) => {
                let n = need.min(rest.len());
                reader.insert(n).copy_from_slice(&rest[..n]);
                reader.notify_read(n);
                rest = &rest[n..];
            }
            Ok(mcap::sans_io::MessageReadEvent::Message(message)) => {
                handle(&message)?;
                messages += 1;
            }
            Err(e) => {
                report(format!(
                    "damaged after {messages} messages and without an index to resume from, \
                     the rest of the file is skipped: {e}"
                ));
                return Ok(1);
            }
        }
    }
    Ok(0)
}
