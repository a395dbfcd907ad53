//! The ROS 2 command-line arguments (`--ros-args ... [--]`), parsed by the node itself because
//! `ros2-client` does not: `--params-file FILE`, `-p name:=value`, `-r from:=to`,
//! `-r __ns:=/ns`, `-r __node:=name`, `--log-level LEVEL`.
//!
//! Parameter values are YAML scalars or flow sequences, as in rcl (`-p period:=4.0`,
//! `-p marker_ids:=[1,2]`, `-p camera_frame:=cam`). Parameter files use the standard layout
//! `<node pattern>: ros__parameters: {...}` where the node pattern is a fully qualified name,
//! a bare node name, or a wildcard (`/**`, `/*/name`); nested maps give dotted names.
//! Command-line `-p` values override parameter files, later files override earlier ones.

use crate::params::ParamValue;
use std::path::PathBuf;
use yaml_rust2::Yaml;

/// A topic remapping rule `[node:]from:=to`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Remap {
    /// Only applies to the node with this name, when given (`node:from:=to`).
    pub node: Option<String>,
    /// Name to match, as written (relative, absolute or `~/private`).
    pub from: String,
    /// Replacement name, as written.
    pub to: String,
}

/// Everything the node takes from `--ros-args` blocks.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RosArgs {
    /// `--params-file` files, in order.
    pub params_files: Vec<PathBuf>,
    /// `-p name:=value` assignments, in order (a `node:` prefix restricts one to that node).
    pub params: Vec<(Option<String>, String, ParamValue)>,
    /// `-r from:=to` rules, in order (the first matching rule wins).
    pub remaps: Vec<Remap>,
    /// `__ns:=` namespace override (absolute).
    pub namespace: Option<String>,
    /// `__node:=` (or `__name:=`) node name override.
    pub node_name: Option<String>,
    /// `--log-level` value (`debug`, `info`, `warn`, `error`, `fatal`), lower case.
    pub log_level: Option<String>,
    /// Arguments outside `--ros-args` blocks (the node accepts none; kept for the message).
    pub other: Vec<String>,
}

/// Why the command line was rejected.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ArgsError(pub String);

impl std::fmt::Display for ArgsError {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ArgsError {}

fn err<T>(message: impl Into<String>) -> Result<T, ArgsError> {
    Err(ArgsError(message.into()))
}

/// Flags rcl accepts that this node ignores (they take no value).
const IGNORED_FLAGS: &[&str] = &[
    "--enable-rosout-logs",
    "--disable-rosout-logs",
    "--enable-stdout-logs",
    "--disable-stdout-logs",
    "--enable-external-lib-logs",
    "--disable-external-lib-logs",
];

impl RosArgs {
    /// Parses the process arguments without the program name.
    pub fn parse<I, S>(args: I) -> Result<RosArgs, ArgsError>
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        let mut out = RosArgs::default();
        let mut args = args.into_iter().map(Into::into);
        let mut in_ros = false;
        while let Some(arg) = args.next() {
            if !in_ros {
                if arg == "--ros-args" {
                    in_ros = true;
                } else {
                    out.other.push(arg);
                }
                continue;
            }
            let mut value_of = |flag: &str| {
                args.next()
                    .ok_or_else(|| ArgsError(format!("`{flag}` needs a value")))
            };
            match arg.as_str() {
                "--" => in_ros = false,
                "--ros-args" => {}
                "-p" | "--param" => {
                    let text = value_of(&arg)?;
                    out.params.push(parse_param_assignment(&text)?);
                }
                "-r" | "--remap" => {
                    let text = value_of(&arg)?;
                    out.add_remap(&text)?;
                }
                "--params-file" => out.params_files.push(PathBuf::from(value_of(&arg)?)),
                "--log-level" => {
                    let level = value_of(&arg)?;
                    // `name:=level` sets a named logger; only the default logger is honoured.
                    let level = level.rsplit(":=").next().unwrap_or(&level).to_lowercase();
                    if !["debug", "info", "warn", "error", "fatal"].contains(&level.as_str()) {
                        return err(format!("unknown log level `{level}`"));
                    }
                    out.log_level = Some(level);
                }
                "-e" | "--enclave" | "--log-config-file" | "--log-file-name" => {
                    value_of(&arg)?;
                }
                flag if IGNORED_FLAGS.contains(&flag) => {}
                other => return err(format!("unknown ROS argument `{other}`")),
            }
        }
        Ok(out)
    }

    fn add_remap(&mut self, text: &str) -> Result<(), ArgsError> {
        let (lhs, to) = text
            .split_once(":=")
            .ok_or_else(|| ArgsError(format!("remapping `{text}` is not `from:=to`")))?;
        let (node, from) = match lhs.split_once(':') {
            Some((node, from)) => (Some(node.to_string()), from),
            None => (None, lhs),
        };
        if from.is_empty() || to.is_empty() {
            return err(format!("remapping `{text}` has an empty side"));
        }
        match from {
            "__ns" => {
                if node.is_none() {
                    self.namespace = Some(normalize_namespace(to)?);
                }
            }
            "__node" | "__name" => {
                if !is_valid_token(to) {
                    return err(format!("invalid node name `{to}`"));
                }
                if node.is_none() {
                    self.node_name = Some(to.to_string());
                }
            }
            _ => self.remaps.push(Remap {
                node,
                from: from.to_string(),
                to: to.to_string(),
            }),
        }
        Ok(())
    }

    /// Resolves a topic name as the node `node` in namespace `namespace` sees it, remapping
    /// applied: `~/x` → `<ns>/<node>/x`, `x` → `<ns>/x`, `/x` unchanged.
    pub fn resolve_topic(&self, name: &str, namespace: &str, node: &str) -> String {
        let resolved = resolve_name(name, namespace, node);
        for rule in &self.remaps {
            if rule.node.as_deref().is_some_and(|n| n != node) {
                continue;
            }
            if resolve_name(&rule.from, namespace, node) == resolved {
                return resolve_name(&rule.to, namespace, node);
            }
        }
        resolved
    }

    /// The parameter values for node `node` in namespace `namespace`: parameter files in
    /// order, then `-p` assignments. Names are dotted for nested maps.
    pub fn parameter_overrides(
        &self,
        namespace: &str,
        node: &str,
    ) -> Result<Vec<(String, ParamValue)>, ArgsError> {
        let mut out = Vec::new();
        for path in &self.params_files {
            let text = vernier::limits::read_text_bounded(
                path,
                vernier::limits::MAX_PARAM_FILE_BYTES,
                "parameter file",
            )
            .map_err(|e| ArgsError(format!("cannot read parameter file {e}")))?;
            out.extend(
                parse_params_file(&text, namespace, node)
                    .map_err(|e| ArgsError(format!("{}: {}", path.display(), e.0)))?,
            );
        }
        for (target, name, value) in &self.params {
            if target.as_deref().is_none_or(|t| t == node) {
                out.push((name.clone(), value.clone()));
            }
        }
        Ok(out)
    }
}

/// `name:=value` with an optional `node:` prefix.
fn parse_param_assignment(text: &str) -> Result<(Option<String>, String, ParamValue), ArgsError> {
    let (lhs, value) = text
        .split_once(":=")
        .ok_or_else(|| ArgsError(format!("parameter `{text}` is not `name:=value`")))?;
    let (node, name) = match lhs.split_once(':') {
        Some((node, name)) => (Some(node.to_string()), name),
        None => (None, lhs),
    };
    if name.is_empty() {
        return err(format!("parameter `{text}` has no name"));
    }
    let docs = vernier::limits::load_yaml(value)
        .map_err(|e| ArgsError(format!("parameter `{name}`: {e}")))?;
    let value = match docs.first() {
        Some(doc) => {
            yaml_to_value(doc).map_err(|e| ArgsError(format!("parameter `{name}`: {e}")))?
        }
        // An empty value is the empty string, as in rcl.
        None => ParamValue::String(String::new()),
    };
    Ok((node, name.to_string(), value))
}

/// Converts a YAML value to a parameter value (scalars and homogeneous sequences).
pub fn yaml_to_value(yaml: &Yaml) -> Result<ParamValue, String> {
    Ok(match yaml {
        Yaml::Boolean(b) => ParamValue::Boolean(*b),
        Yaml::Integer(i) => ParamValue::Integer(*i),
        Yaml::Real(text) => ParamValue::Double(
            yaml.as_f64()
                .ok_or_else(|| format!("`{text}` is not a number"))?,
        ),
        Yaml::String(s) => ParamValue::String(s.clone()),
        Yaml::Array(items) => array_value(items)?,
        Yaml::Null => return Err("no value (null)".into()),
        Yaml::Hash(_) => return Err("a map is not a parameter value".into()),
        Yaml::Alias(_) | Yaml::BadValue => return Err("unsupported YAML value".into()),
    })
}

fn array_value(items: &[Yaml]) -> Result<ParamValue, String> {
    let all = |f: fn(&Yaml) -> bool| items.iter().all(f);
    if items.is_empty() {
        // The type of an empty list is unknown: the declared type decides (see params.rs).
        return Ok(ParamValue::StringArray(Vec::new()));
    }
    if all(|y| matches!(y, Yaml::Boolean(_))) {
        return Ok(ParamValue::BooleanArray(
            items.iter().filter_map(Yaml::as_bool).collect(),
        ));
    }
    if all(|y| matches!(y, Yaml::Integer(_))) {
        return Ok(ParamValue::IntegerArray(
            items.iter().filter_map(Yaml::as_i64).collect(),
        ));
    }
    if all(|y| matches!(y, Yaml::Integer(_) | Yaml::Real(_))) {
        let mut out = Vec::with_capacity(items.len());
        for y in items {
            out.push(match y {
                Yaml::Integer(i) => *i as f64,
                other => other.as_f64().ok_or("not a number in a number list")?,
            });
        }
        return Ok(ParamValue::DoubleArray(out));
    }
    if all(|y| matches!(y, Yaml::String(_))) {
        return Ok(ParamValue::StringArray(
            items
                .iter()
                .filter_map(|y| y.as_str().map(String::from))
                .collect(),
        ));
    }
    Err("a list must hold values of one type (bool, integer, double or string)".into())
}

/// Parses a ROS 2 parameter file and returns the values that apply to `namespace`/`node`.
pub fn parse_params_file(
    text: &str,
    namespace: &str,
    node: &str,
) -> Result<Vec<(String, ParamValue)>, ArgsError> {
    let docs = vernier::limits::load_yaml(text).map_err(|e| ArgsError(format!("bad YAML: {e}")))?;
    let fq_node = fully_qualified(namespace, node);
    let mut out = Vec::new();
    for doc in &docs {
        let Yaml::Hash(entries) = doc else {
            return err("top level must map node names to `ros__parameters`");
        };
        for (key, body) in entries {
            let pattern = key
                .as_str()
                .ok_or_else(|| ArgsError("node names must be strings".into()))?;
            // Every entry must be well formed, matching this node or not.
            let params = match body {
                Yaml::Hash(inner) => inner.get(&Yaml::String("ros__parameters".into())),
                _ => None,
            };
            let Some(params) = params else {
                return err(format!("`{pattern}` has no `ros__parameters` map"));
            };
            let mut values = Vec::new();
            flatten_params("", params, &mut values)?;
            if node_pattern_matches(pattern, &fq_node) {
                out.extend(values);
            }
        }
    }
    Ok(out)
}

fn flatten_params(
    prefix: &str,
    yaml: &Yaml,
    out: &mut Vec<(String, ParamValue)>,
) -> Result<(), ArgsError> {
    let Yaml::Hash(entries) = yaml else {
        return err("`ros__parameters` must be a map");
    };
    for (key, value) in entries {
        let key = match key {
            Yaml::String(s) => s.clone(),
            Yaml::Integer(i) => i.to_string(),
            _ => return err("parameter names must be strings"),
        };
        let name = if prefix.is_empty() {
            key
        } else {
            format!("{prefix}.{key}")
        };
        match value {
            Yaml::Hash(_) => flatten_params(&name, value, out)?,
            _ => out.push((
                name.clone(),
                yaml_to_value(value).map_err(|e| ArgsError(format!("parameter `{name}`: {e}")))?,
            )),
        }
    }
    Ok(())
}

/// Whether a parameter-file key (`/**`, `/ns/node`, `node`, `/*/node`, `/**/node`) selects
/// the fully qualified node name `fq_node`.
pub fn node_pattern_matches(pattern: &str, fq_node: &str) -> bool {
    let pattern = pattern.strip_prefix('/').unwrap_or(pattern);
    let pattern_tokens: Vec<&str> = pattern.split('/').filter(|t| !t.is_empty()).collect();
    let node_tokens: Vec<&str> = fq_node.split('/').filter(|t| !t.is_empty()).collect();
    // A bare node name (no slash) means that node in the root namespace, as in rcl.
    glob_tokens(&pattern_tokens, &node_tokens)
}

fn glob_tokens(pattern: &[&str], name: &[&str]) -> bool {
    match pattern.split_first() {
        None => name.is_empty(),
        Some((&"**", rest)) => (0..=name.len()).any(|skip| glob_tokens(rest, &name[skip..])),
        Some((&first, rest)) => match name.split_first() {
            Some((&token, name_rest)) => {
                (first == "*" || first == token) && glob_tokens(rest, name_rest)
            }
            None => false,
        },
    }
}

/// `namespace` + `node` as `/ns/node` (root namespace: `/node`).
pub fn fully_qualified(namespace: &str, node: &str) -> String {
    let ns = namespace.trim_end_matches('/');
    format!("{ns}/{node}")
}

/// Resolves `name` (relative, absolute or private `~`) to an absolute topic name.
pub fn resolve_name(name: &str, namespace: &str, node: &str) -> String {
    let ns = namespace.trim_end_matches('/');
    if let Some(private) = name.strip_prefix('~') {
        let private = private.trim_start_matches('/');
        if private.is_empty() {
            format!("{ns}/{node}")
        } else {
            format!("{ns}/{node}/{private}")
        }
    } else if name.starts_with('/') {
        name.to_string()
    } else {
        format!("{ns}/{name}")
    }
}

/// Accepts `ns`, `/ns`, `/a/b/`; returns `/ns` or `/` for the root.
fn normalize_namespace(ns: &str) -> Result<String, ArgsError> {
    let trimmed = ns.trim_matches('/');
    if trimmed.is_empty() {
        return Ok("/".into());
    }
    if !trimmed.split('/').all(is_valid_token) {
        return err(format!("invalid namespace `{ns}`"));
    }
    Ok(format!("/{trimmed}"))
}

/// A ROS name token: letters, digits, underscores; not starting with a digit, no `__`.
pub fn is_valid_token(token: &str) -> bool {
    !token.is_empty()
        && token.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !token.starts_with(|c: char| c.is_ascii_digit())
        && !token.contains("__")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<RosArgs, ArgsError> {
        RosArgs::parse(args.iter().copied())
    }

    #[test]
    fn parses_params_remaps_namespace_and_node() {
        let args = parse(&[
            "--ros-args",
            "-p",
            "period:=4.0",
            "--param",
            "marker_ids:=[1, 2]",
            "-p",
            "camera_frame:=cam_optical",
            "-p",
            "publish_tf:=false",
            "-p",
            "relative_pairs:=['0:1']",
            "-r",
            "image:=/camera/image_raw",
            "-r",
            "__ns:=/bench",
            "-r",
            "__node:=vernier",
            "--params-file",
            "/tmp/x.yaml",
            "--log-level",
            "WARN",
            "--",
            "extra",
        ])
        .unwrap_or_default();
        assert_eq!(
            args.params,
            vec![
                (None, "period".into(), ParamValue::Double(4.0)),
                (
                    None,
                    "marker_ids".into(),
                    ParamValue::IntegerArray(vec![1, 2])
                ),
                (
                    None,
                    "camera_frame".into(),
                    ParamValue::String("cam_optical".into())
                ),
                (None, "publish_tf".into(), ParamValue::Boolean(false)),
                (
                    None,
                    "relative_pairs".into(),
                    ParamValue::StringArray(vec!["0:1".into()])
                ),
            ]
        );
        assert_eq!(args.namespace.as_deref(), Some("/bench"));
        assert_eq!(args.node_name.as_deref(), Some("vernier"));
        assert_eq!(args.params_files, vec![PathBuf::from("/tmp/x.yaml")]);
        assert_eq!(args.log_level.as_deref(), Some("warn"));
        assert_eq!(args.other, vec!["extra".to_string()]);
        assert_eq!(
            args.resolve_topic("image", "/bench", "vernier"),
            "/camera/image_raw"
        );
        assert_eq!(
            args.resolve_topic("~/markers", "/bench", "vernier"),
            "/bench/vernier/markers"
        );
    }

    #[test]
    fn rejects_malformed_arguments() {
        for bad in [
            &["--ros-args", "-p"][..],
            &["--ros-args", "-p", "period=4"],
            &["--ros-args", "-r", "image"],
            &["--ros-args", "-r", ":=x"],
            &["--ros-args", "--params-file"],
            &["--ros-args", "--bogus"],
            &["--ros-args", "-r", "__node:=2bad"],
            &["--ros-args", "-r", "__ns:=/a b"],
            &["--ros-args", "--log-level", "loud"],
            &["--ros-args", "-p", "ids:=[1, a]"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?} accepted");
        }
        // Arguments before --ros-args are not ROS arguments.
        let args = parse(&["-p", "x:=1"]).unwrap_or_default();
        assert!(args.params.is_empty());
        assert_eq!(args.other.len(), 2);
    }

    #[test]
    fn remaps_resolve_relative_private_and_node_specific_names() {
        let args = parse(&[
            "--ros-args",
            "-r",
            "other_node:image:=/wrong",
            "-r",
            "~/markers:=/out/markers",
            "-r",
            "/abs:=rel",
        ])
        .unwrap_or_default();
        assert_eq!(args.resolve_topic("image", "/", "det"), "/image");
        assert_eq!(args.resolve_topic("~/markers", "/", "det"), "/out/markers");
        assert_eq!(args.resolve_topic("/abs", "/ns", "det"), "/ns/rel");
        assert_eq!(args.resolve_topic("/tf", "/ns", "det"), "/tf");
        assert_eq!(resolve_name("~", "/a/b", "n"), "/a/b/n");
    }

    #[test]
    fn parameter_files_match_node_patterns_and_flatten() {
        let yaml = r#"
/**:
  ros__parameters:
    period: 4.0
    marker_ids: [3, 4]
other_node:
  ros__parameters:
    period: 9.0
/bench/vernier:
  ros__parameters:
    camera_frame: cam
    nested:
      level: 2
"#;
        let got = parse_params_file(yaml, "/bench", "vernier").unwrap_or_default();
        assert_eq!(
            got,
            vec![
                ("period".into(), ParamValue::Double(4.0)),
                ("marker_ids".into(), ParamValue::IntegerArray(vec![3, 4])),
                ("camera_frame".into(), ParamValue::String("cam".into())),
                ("nested.level".into(), ParamValue::Integer(2)),
            ]
        );
        assert!(node_pattern_matches("vernier", "/vernier"));
        assert!(!node_pattern_matches("vernier", "/bench/vernier"));
        assert!(node_pattern_matches("/*/vernier", "/bench/vernier"));
        assert!(node_pattern_matches("/**/vernier", "/a/b/vernier"));
        assert!(!node_pattern_matches("/*/vernier", "/a/b/vernier"));
        assert!(parse_params_file("period: 4", "/", "n").is_err());
        assert!(parse_params_file("/**:\n  period: 4\n", "/", "n").is_err());
    }

    #[test]
    fn command_line_overrides_parameter_files() {
        let dir = std::env::temp_dir().join(format!("vernier_ros_args_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or(());
        let file = dir.join("p.yaml");
        std::fs::write(
            &file,
            "/**:\n  ros__parameters:\n    period: 4.0\n    max_rate: 10.0\n",
        )
        .unwrap_or(());
        let file_arg = file.display().to_string();
        let args = parse(&[
            "--ros-args",
            "-p",
            "period:=5.5",
            "--params-file",
            &file_arg,
            "-p",
            "other:period:=1.0",
        ])
        .unwrap_or_default();
        let values = args.parameter_overrides("/", "vernier").unwrap_or_default();
        std::fs::remove_dir_all(&dir).unwrap_or(());
        // File first, then -p (which wins); the `other:` assignment is for another node.
        assert_eq!(
            values,
            vec![
                ("period".into(), ParamValue::Double(4.0)),
                ("max_rate".into(), ParamValue::Double(10.0)),
                ("period".into(), ParamValue::Double(5.5)),
            ]
        );
        let missing = parse(&["--ros-args", "--params-file", "/nonexistent/p.yaml"])
            .unwrap_or_default()
            .parameter_overrides("/", "vernier");
        assert!(missing.is_err());
    }

    #[test]
    fn yaml_bombs_are_refused() {
        let mut bomb =
            String::from("/**:\n  ros__parameters:\n    a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n");
        for i in 1..12 {
            let refs = vec![format!("*a{}", i - 1); 10].join(", ");
            bomb.push_str(&format!("    a{i}: &a{i} [{refs}]\n"));
        }
        let e = parse_params_file(&bomb, "/", "vernier")
            .err()
            .unwrap_or(ArgsError(String::new()));
        assert!(e.0.contains("nodes"), "{e}");
        let deep = format!("period:={}{}", "[".repeat(500), "]".repeat(500));
        assert!(parse(&["--ros-args", "-p", &deep]).is_err());
    }
}
