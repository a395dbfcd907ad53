//! JSON pattern-description files (docs/design.md#pattern-file): reading any layout class, writing
//! it back.
//!
//! A file is a JSON object whose **first member name is the class name** and whose value holds
//! the fields; later members are ignored. Reading is more tolerant than the original: doubles
//! may be written with or without a decimal point (`15` or `15.0`); integers must be integers;
//! unknown keys (e.g. `copyright`) are ignored. Writing follows the original's layout
//! (4-space indentation, its key order, doubles of class fields with 15 decimals) but always
//! writes doubles with a decimal point or exponent, so the files are readable by both
//! implementations and `JSON → Pattern → JSON` reproduces the text.
//!
//! Extensions over the original, written only when they differ from the default (the original
//! ignores unknown keys): `dotSize` for Periodic and Megarena, `id` for HP codes, and
//! `bitSequence` for Megarena layouts built from a user-supplied sequence. `date` is written
//! only when set (the original writes the current time instead of an empty date).

use std::fmt;
use std::path::Path;

use serde::de::{Deserialize, Deserializer, IgnoredAny, MapAccess, Visitor};
use serde_json::{Map, Value};

use crate::error::{Error, Result};
use crate::layout::{
    BitmapLayout, CustomDot, CustomLayout, FingerprintLayout, HpCodeLayout, Layout, Margins,
    MegarenaLayout, Metadata, PeriodicLayout, Rect,
};
use crate::megarena_sequence::{LineSequence, SequenceSource, MAX_CODE_DEPTH, MIN_CODE_DEPTH};

/// Class names accepted as the first member of a pattern file.
pub const CLASS_NAMES: [&str; 6] = [
    "PeriodicPattern",
    "HPCodePattern",
    "BitmapPattern",
    "FingerprintPattern",
    "MegarenaPattern",
    "CustomPattern",
];

/// A layout of any class, as stored in a JSON pattern file.
#[derive(Clone, Debug, PartialEq)]
pub enum Pattern {
    /// `PeriodicPattern`.
    Periodic(PeriodicLayout),
    /// `HPCodePattern`.
    HpCode(HpCodeLayout),
    /// `BitmapPattern` (also used for stamps).
    Bitmap(BitmapLayout),
    /// `FingerprintPattern`.
    Fingerprint(FingerprintLayout),
    /// `MegarenaPattern`.
    Megarena(MegarenaLayout),
    /// `CustomPattern`.
    Custom(CustomLayout),
}

impl Pattern {
    /// The layout, as a trait object (rendering, export).
    pub fn layout(&self) -> &dyn Layout {
        match self {
            Pattern::Periodic(l) => l,
            Pattern::HpCode(l) => l,
            Pattern::Bitmap(l) => l,
            Pattern::Fingerprint(l) => l,
            Pattern::Megarena(l) => l,
            Pattern::Custom(l) => l,
        }
    }

    /// Class name used in pattern files (`"PeriodicPattern"`, ...).
    pub fn class_name(&self) -> &'static str {
        self.layout().class_name()
    }

    /// Descriptive metadata and margins.
    pub fn metadata(&self) -> &Metadata {
        self.layout().metadata()
    }

    /// Parses a pattern file's text. Malformed JSON gives [`Error::Json`] (with line and
    /// column); invalid content gives [`Error::InvalidPattern`] naming the offending key.
    pub fn from_json_str(text: &str) -> Result<Self> {
        Self::parse(text, None)
    }

    /// Reads a pattern file. I/O failures give [`Error::Io`], malformed JSON [`Error::Json`]
    /// with the path.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let size = std::fs::metadata(path)
            .map_err(|source| Error::Io {
                path: path.to_path_buf(),
                source,
            })?
            .len();
        if size > crate::limits::MAX_PATTERN_FILE_BYTES {
            return Err(Error::pattern(
                "<file>",
                format!(
                    "{} is {size} bytes, above the limit of {} bytes for pattern files",
                    path.display(),
                    crate::limits::MAX_PATTERN_FILE_BYTES
                ),
            ));
        }
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, Some(path))
    }

    /// The pattern file text (4-space indentation, trailing newline).
    pub fn to_json_string(&self) -> String {
        let mut members = Members::default();
        let meta = self.metadata();
        members.string_if_set("description", &meta.description);
        members.string_if_set("unit", &meta.unit);
        let m = meta.margins;
        for (key, value) in [
            ("leftMargin", m.left),
            ("rightMargin", m.right),
            ("topMargin", m.top),
            ("bottomMargin", m.bottom),
        ] {
            if value > 0.0 {
                members.push(key, shortest_double(value));
            }
        }
        self.write_class_fields(&mut members);
        members.string_if_set("author", &meta.author);
        members.string_if_set("date", &meta.date);
        format!(
            "{{\n    \"{}\": {{\n{}\n    }}\n}}\n",
            self.class_name(),
            members.0.join(",\n")
        )
    }

    /// Writes [`Pattern::to_json_string`] to `path`.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        crate::output::write_file(path, self.to_json_string().as_bytes()).map_err(|source| {
            Error::Io {
                path: path.to_path_buf(),
                source,
            }
        })
    }

    fn parse(text: &str, path: Option<&Path>) -> Result<Self> {
        let FirstMember(first) = serde_json::from_str(text).map_err(|e| Error::Json {
            path: path.map(Path::to_path_buf),
            reason: e.to_string(),
        })?;
        let Some((class, body)) = first else {
            return Err(Error::pattern(
                "<root>",
                "empty object: the first member must name the pattern class",
            ));
        };
        let Value::Object(map) = body else {
            return Err(Error::pattern(
                class,
                format!("must be an object of fields, got {}", describe(&body)),
            ));
        };
        let fields = Fields(&map);
        let metadata = fields.metadata()?;
        let pattern = match class.as_str() {
            "PeriodicPattern" => Pattern::Periodic(fields.periodic()?.with_metadata(metadata)),
            "HPCodePattern" => Pattern::HpCode(fields.hp_code()?.with_metadata(metadata)),
            "BitmapPattern" => {
                let period = fields.required_f64("period")?;
                let rows = fields.bit_rows("bitmap")?;
                Pattern::Bitmap(BitmapLayout::from_rows(period, &rows)?.with_metadata(metadata))
            }
            "FingerprintPattern" => {
                let period = fields.required_f64("period")?;
                let rows = fields.bit_rows("bitmap")?;
                Pattern::Fingerprint(
                    FingerprintLayout::from_rows(period, &rows)?.with_metadata(metadata),
                )
            }
            "MegarenaPattern" => Pattern::Megarena(fields.megarena()?.with_metadata(metadata)),
            "CustomPattern" => Pattern::Custom(fields.custom()?.with_metadata(metadata)),
            _ => {
                return Err(Error::pattern(
                    class,
                    format!(
                        "unknown pattern class; expected one of {}",
                        CLASS_NAMES.join(", ")
                    ),
                ))
            }
        };
        Ok(pattern)
    }

    fn write_class_fields(&self, members: &mut Members) {
        match self {
            Pattern::Periodic(l) => {
                members.push("period", class_double(l.period()));
                members.push("nRows", l.n_rows().to_string());
                members.push("nCols", l.n_cols().to_string());
                if l.dot_size() != l.period() / 2.0 {
                    members.push("dotSize", class_double(l.dot_size()));
                }
            }
            Pattern::HpCode(l) => {
                members.push("period", class_double(l.period()));
                members.push("size", l.size().to_string());
                if l.id() != 0 {
                    members.push("id", l.id().to_string());
                }
            }
            Pattern::Bitmap(l) => {
                members.push("period", class_double(l.period()));
                members.push("bitmap", bit_rows_text(&l.rows()));
            }
            Pattern::Fingerprint(l) => {
                members.push("period", class_double(l.period()));
                members.push("bitmap", bit_rows_text(&l.rows()));
            }
            Pattern::Megarena(l) => {
                let sequence = l.sequence();
                match sequence.source() {
                    SequenceSource::Generated => {
                        members.push("codeDepth", sequence.code_depth().to_string());
                    }
                    SequenceSource::UserSupplied => {
                        members.push("bitSequence", format!("[{}]", join_bits(sequence.bits())));
                    }
                }
                members.push("period", class_double(l.period()));
                let roi = l.region_of_interest();
                // The original's spacing, including the blank before `]`.
                members.push(
                    "regionOfInterest",
                    format!(
                        "[{}, {}, {}, {} ]",
                        class_double(roi.x),
                        class_double(roi.y),
                        class_double(roi.width),
                        class_double(roi.height)
                    ),
                );
                if l.dot_size() != l.period() / 2.0 {
                    members.push("dotSize", class_double(l.dot_size()));
                }
            }
            Pattern::Custom(l) => {
                let rows: Vec<String> = l
                    .dots()
                    .iter()
                    .map(|d| {
                        let r = d.rect;
                        let values = [r.x, r.y, r.width, r.height, d.intensity];
                        let values: Vec<String> = values.into_iter().map(shortest_double).collect();
                        format!("            [{}]", values.join(", "))
                    })
                    .collect();
                members.push("dots", format!("[\n{}\n        ]", rows.join(",\n")));
            }
        }
    }
}

macro_rules! impl_from_layout {
    ($($layout:ty => $variant:ident),* $(,)?) => {$(
        impl From<$layout> for Pattern {
            fn from(layout: $layout) -> Self {
                Pattern::$variant(layout)
            }
        }
    )*};
}

impl_from_layout!(
    PeriodicLayout => Periodic,
    HpCodeLayout => HpCode,
    BitmapLayout => Bitmap,
    FingerprintLayout => Fingerprint,
    MegarenaLayout => Megarena,
    CustomLayout => Custom,
);

// ---------------------------------------------------------------------------------------------
// Reading

/// The first member of the top-level object (`None` for `{}`); the rest is skipped unparsed
/// into values, which keeps the file's member order without an order-preserving map.
struct FirstMember(Option<(String, Value)>);

impl<'de> Deserialize<'de> for FirstMember {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> std::result::Result<Self, D::Error> {
        struct FirstMemberVisitor;
        impl<'de> Visitor<'de> for FirstMemberVisitor {
            type Value = FirstMember;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a JSON object whose first member is the pattern class")
            }
            fn visit_map<A: MapAccess<'de>>(
                self,
                mut map: A,
            ) -> std::result::Result<FirstMember, A::Error> {
                let first = map.next_entry::<String, Value>()?;
                while map.next_entry::<IgnoredAny, IgnoredAny>()?.is_some() {}
                Ok(FirstMember(first))
            }
        }
        deserializer.deserialize_map(FirstMemberVisitor)
    }
}

/// Short description of a JSON value for error messages.
fn describe(value: &Value) -> String {
    match value {
        Value::Null => "null".into(),
        Value::Bool(b) => format!("boolean {b}"),
        Value::Number(n) => n.to_string(),
        Value::String(s) if s.chars().count() <= 40 => format!("string {value}"),
        Value::String(_) => "a string".into(),
        Value::Array(a) => format!("an array of {} entries", a.len()),
        Value::Object(_) => "an object".into(),
    }
}

/// Typed access to the fields of a pattern object; every error names its key.
struct Fields<'a>(&'a Map<String, Value>);

impl Fields<'_> {
    fn optional_f64(&self, key: &str) -> Result<Option<f64>> {
        match self.0.get(key) {
            None => Ok(None),
            Some(v) => v.as_f64().map(Some).ok_or_else(|| {
                Error::pattern(key, format!("must be a number, got {}", describe(v)))
            }),
        }
    }

    fn required_f64(&self, key: &str) -> Result<f64> {
        let value = self.optional_f64(key)?.ok_or_else(|| missing(key))?;
        if key == "period" {
            // The one range of every period setting (CLI, node, pattern files).
            crate::limits::check_period(value).map_err(|e| match e {
                Error::InvalidParameter { reason, .. } => Error::pattern(key, reason),
                other => other,
            })?;
        }
        Ok(value)
    }

    fn optional_int(&self, key: &str) -> Result<Option<i64>> {
        match self.0.get(key) {
            None => Ok(None),
            Some(v) => v.as_i64().map(Some).ok_or_else(|| {
                Error::pattern(
                    key,
                    format!("must be an integer (no decimal point), got {}", describe(v)),
                )
            }),
        }
    }

    /// Required non-negative integer; `what` describes the accepted values for the message.
    fn required_count(&self, key: &str, what: &str) -> Result<usize> {
        let n = self.optional_int(key)?.ok_or_else(|| missing(key))?;
        usize::try_from(n).map_err(|_| Error::pattern(key, format!("must be {what}, got {n}")))
    }

    fn string(&self, key: &str) -> Result<String> {
        match self.0.get(key) {
            None => Ok(String::new()),
            Some(Value::String(s)) => Ok(s.clone()),
            Some(v) => Err(Error::pattern(
                key,
                format!("must be a string, got {}", describe(v)),
            )),
        }
    }

    fn margin(&self, key: &str) -> Result<Option<f64>> {
        match self.optional_f64(key)? {
            Some(m) if !(m.is_finite() && m >= 0.0) => Err(Error::pattern(
                key,
                format!("must be a non-negative number, got {m}"),
            )),
            other => Ok(other),
        }
    }

    fn metadata(&self) -> Result<Metadata> {
        // `margin` sets all four; the individual keys then override it.
        let all = self.margin("margin")?.unwrap_or(0.0);
        let margins = Margins {
            left: self.margin("leftMargin")?.unwrap_or(all),
            right: self.margin("rightMargin")?.unwrap_or(all),
            top: self.margin("topMargin")?.unwrap_or(all),
            bottom: self.margin("bottomMargin")?.unwrap_or(all),
        };
        Ok(Metadata {
            description: self.string("description")?,
            date: self.string("date")?,
            author: self.string("author")?,
            unit: self.string("unit")?,
            margins,
        })
    }

    /// A 0/1 integer, `at` locating it inside `key` for messages.
    fn bit(key: &str, value: &Value, at: &dyn Fn() -> String) -> Result<u8> {
        match value.as_i64() {
            Some(0) => Ok(0),
            Some(1) => Ok(1),
            _ => Err(Error::pattern(
                key,
                format!("{} must be 0 or 1, got {}", at(), describe(value)),
            )),
        }
    }

    /// Array of 0/1 integers.
    fn bit_array(key: &str, value: &Value, row: Option<usize>) -> Result<Vec<u8>> {
        let Value::Array(entries) = value else {
            let what = row.map_or_else(|| "value".to_string(), |r| format!("row {r}"));
            return Err(Error::pattern(
                key,
                format!(
                    "{what} must be an array of 0/1 integers, got {}",
                    describe(value)
                ),
            ));
        };
        entries
            .iter()
            .enumerate()
            .map(|(j, v)| {
                Self::bit(key, v, &|| match row {
                    Some(i) => format!("entry [{i}][{j}]"),
                    None => format!("entry {j}"),
                })
            })
            .collect()
    }

    /// Required array of rows of 0/1 integers (the `bitmap` key).
    fn bit_rows(&self, key: &str) -> Result<Vec<Vec<u8>>> {
        match self.0.get(key) {
            None => Err(missing(key)),
            Some(Value::Array(rows)) => rows
                .iter()
                .enumerate()
                .map(|(i, row)| Self::bit_array(key, row, Some(i)))
                .collect(),
            Some(v) => Err(Error::pattern(
                key,
                format!(
                    "must be an array of rows of 0/1 integers, got {}",
                    describe(v)
                ),
            )),
        }
    }

    /// Array of exactly `N` numbers.
    fn numbers<const N: usize>(key: &str, value: &Value, at: &str) -> Result<[f64; N]> {
        let bad = || {
            Error::pattern(
                key,
                format!(
                    "{at}must be an array of {N} numbers, got {}",
                    describe(value)
                ),
            )
        };
        let Value::Array(entries) = value else {
            return Err(bad());
        };
        if entries.len() != N {
            return Err(bad());
        }
        let mut out = [0.0; N];
        for (slot, entry) in out.iter_mut().zip(entries) {
            *slot = entry.as_f64().ok_or_else(bad)?;
        }
        Ok(out)
    }

    fn periodic(&self) -> Result<PeriodicLayout> {
        let period = self.required_f64("period")?;
        let n_rows = self.required_count("nRows", "a positive odd integer")?;
        let n_cols = self.required_count("nCols", "a positive odd integer")?;
        match self.optional_f64("dotSize")? {
            Some(dot_size) => PeriodicLayout::with_dot_size(period, n_rows, n_cols, dot_size),
            None => PeriodicLayout::new(period, n_rows, n_cols),
        }
    }

    fn hp_code(&self) -> Result<HpCodeLayout> {
        let period = self.required_f64("period")?;
        let size = self.required_count("size", "a positive odd integer")?;
        let layout = HpCodeLayout::new(period, size)?;
        match self.optional_int("id")? {
            None => Ok(layout),
            Some(id) => {
                let id = u64::try_from(id).map_err(|_| {
                    Error::pattern("id", format!("must be a non-negative integer, got {id}"))
                })?;
                layout.with_id(id)
            }
        }
    }

    fn code_depth(&self, key: &str) -> Result<Option<LineSequence>> {
        let Some(depth) = self.optional_int(key)? else {
            return Ok(None);
        };
        let range = i64::from(MIN_CODE_DEPTH)..=i64::from(MAX_CODE_DEPTH);
        match u32::try_from(depth) {
            Ok(d) if range.contains(&depth) => LineSequence::generated(d).map(Some),
            _ => Err(Error::pattern(
                key,
                format!("must be an integer in {MIN_CODE_DEPTH}..={MAX_CODE_DEPTH}, got {depth}"),
            )),
        }
    }

    fn megarena(&self) -> Result<MegarenaLayout> {
        let period = self.required_f64("period")?;
        // Checked in the original's order: bitSequence, codeDepth, codeSize.
        let sequence = match self.0.get("bitSequence") {
            Some(value) => LineSequence::from_bits(Self::bit_array("bitSequence", value, None)?)?,
            None => match self.code_depth("codeDepth")? {
                Some(sequence) => sequence,
                None => self.code_depth("codeSize")?.ok_or_else(|| {
                    Error::pattern(
                        "codeDepth",
                        "missing: one of `bitSequence`, `codeDepth` or `codeSize` is required",
                    )
                })?,
            },
        };
        let mut layout = MegarenaLayout::from_sequence(period, sequence)?;
        if let Some(dot_size) = self.optional_f64("dotSize")? {
            layout = layout.with_dot_size(dot_size)?;
        }
        if let Some(value) = self.0.get("regionOfInterest") {
            let [x, y, w, h] = Self::numbers::<4>("regionOfInterest", value, "")?;
            layout = layout.with_region_of_interest(Rect::new(x, y, w, h))?;
        }
        Ok(layout)
    }

    fn custom(&self) -> Result<CustomLayout> {
        let entries = match self.0.get("dots") {
            None => return Err(missing("dots")),
            Some(Value::Array(entries)) => entries,
            Some(v) => {
                return Err(Error::pattern(
                    "dots",
                    format!(
                        "must be an array of [x, y, w, h, intensity] entries, got {}",
                        describe(v)
                    ),
                ))
            }
        };
        let dots = entries
            .iter()
            .enumerate()
            .map(|(i, entry)| {
                let [x, y, w, h, intensity] =
                    Self::numbers::<5>("dots", entry, &format!("entry {i} "))?;
                Ok(CustomDot::new(x, y, w, h, intensity))
            })
            .collect::<Result<Vec<_>>>()?;
        CustomLayout::new(dots)
    }
}

fn missing(key: &str) -> Error {
    Error::pattern(key, "required key is missing")
}

// ---------------------------------------------------------------------------------------------
// Writing

/// The members of the class object, already formatted as `"key": value`.
#[derive(Default)]
struct Members(Vec<String>);

impl Members {
    fn push(&mut self, key: &str, value: String) {
        self.0.push(format!("        \"{key}\": {value}"));
    }
    fn string_if_set(&mut self, key: &str, value: &str) {
        if !value.is_empty() {
            // `Value`'s Display escapes as JSON and cannot fail.
            self.push(key, Value::String(value.to_owned()).to_string());
        }
    }
}

/// A class-field double as the original writes it (fixed, 15 decimals) when that text reads
/// back as the same value, else the shortest exact form; always with a point or exponent.
fn class_double(value: f64) -> String {
    let fixed = format!("{value:.15}");
    if value.abs() < 1e15 && fixed.parse::<f64>() == Ok(value) {
        fixed
    } else {
        shortest_double(value)
    }
}

/// Shortest text that reads back as `value`, always with a decimal point or exponent
/// (`10.0`, `0.1`, `1e-7`): a JSON number that the original reads as a double.
fn shortest_double(value: f64) -> String {
    format!("{value:?}")
}

fn join_bits(bits: &[u8]) -> String {
    bits.iter()
        .map(|b| b.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// `bitmap` value: one row per line, as the original writes it.
fn bit_rows_text(rows: &[Vec<u8>]) -> String {
    let rows: Vec<String> = rows
        .iter()
        .map(|row| format!("            [{}]", join_bits(row)))
        .collect();
    format!("[\n{}\n        ]", rows.join(",\n"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_periodic_with_integer_doubles_and_margin() {
        let text = r#"{"PeriodicPattern": {"period": 15, "nRows": 3, "nCols": 5,
            "margin": 2, "topMargin": 1.5, "unit": "um", "copyright": "x"}, "Other": 1}"#;
        let p = Pattern::from_json_str(text).unwrap();
        assert_eq!(p.class_name(), "PeriodicPattern");
        assert_eq!(p.layout().period(), 15.0);
        let m = p.metadata().margins;
        assert_eq!((m.left, m.right, m.top, m.bottom), (2.0, 2.0, 1.5, 2.0));
        assert_eq!(p.metadata().unit, "um");
    }

    #[test]
    fn first_member_wins() {
        let text = r#"{"ZClass": {}, "PeriodicPattern": {"period": 1.0, "nRows": 3, "nCols": 3}}"#;
        let e = Pattern::from_json_str(text).unwrap_err().to_string();
        assert!(
            e.contains("`ZClass`") && e.contains("unknown pattern class"),
            "{e}"
        );
    }

    #[test]
    fn errors_name_the_key() {
        let check = |text: &str, needle: &str| {
            let e = Pattern::from_json_str(text).unwrap_err().to_string();
            assert!(e.contains(needle), "`{needle}` not in: {e}");
        };
        check(
            r#"{"PeriodicPattern": {"period": 1.0, "nRows": 4, "nCols": 3}}"#,
            "key `nRows`: must be a positive odd integer, got 4",
        );
        check(
            r#"{"PeriodicPattern": {"period": 1.0, "nRows": 3.0, "nCols": 3}}"#,
            "key `nRows`: must be an integer",
        );
        check(
            r#"{"PeriodicPattern": {"period": "1", "nRows": 3, "nCols": 3}}"#,
            "key `period`: must be a number, got string \"1\"",
        );
        check(
            r#"{"PeriodicPattern": {"nRows": 3, "nCols": 3}}"#,
            "key `period`: required key is missing",
        );
        check(
            r#"{"PeriodicPattern": {"period": 1.0, "nRows": -3, "nCols": 3}}"#,
            "key `nRows`",
        );
        check(
            r#"{"MegarenaPattern": {"period": 1.0}}"#,
            "key `codeDepth`: missing",
        );
        check(
            r#"{"MegarenaPattern": {"period": 1.0, "codeSize": 13}}"#,
            "key `codeSize`",
        );
        check(
            r#"{"MegarenaPattern": {"period": 1.0, "codeSize": 8, "regionOfInterest": [1, 2]}}"#,
            "key `regionOfInterest`",
        );
        check(
            r#"{"BitmapPattern": {"period": 1.0, "bitmap": [[1, 2]]}}"#,
            "entry [0][1] must be 0 or 1",
        );
        check(
            r#"{"CustomPattern": {"dots": [[0, 0, 1, 1]]}}"#,
            "key `dots`: entry 0 must be",
        );
        check(
            r#"{"HPCodePattern": {"period": 1.0, "size": 17, "id": 600}}"#,
            "key `id`",
        );
        check(
            r#"{"HPCodePattern": [1]}"#,
            "key `HPCodePattern`: must be an object",
        );
        check(
            r#"{"PeriodicPattern": {"period": 1.0, "nRows": 3, "nCols": 3, "author": 1}}"#,
            "key `author`",
        );
        check("{}", "empty object");
        check("[1, 2]", "malformed JSON");
        check(
            "{\"PeriodicPattern\": {\n \"period\": 1.0,\n}}",
            "line 3 column 1",
        );
    }

    #[test]
    fn megarena_key_order_and_user_sequence() {
        let text = r#"{"MegarenaPattern": {"period": 2.0, "codeSize": 5, "codeDepth": 4}}"#;
        let Pattern::Megarena(l) = Pattern::from_json_str(text).unwrap() else {
            panic!("wrong class")
        };
        assert_eq!(l.code_depth(), 4, "codeDepth is checked before codeSize");
        let text = r#"{"MegarenaPattern": {"period": 2.0, "bitSequence": [1, 0, 1, 1, 1, 1], "codeDepth": 4}}"#;
        let p = Pattern::from_json_str(text).unwrap();
        let Pattern::Megarena(l) = &p else {
            panic!("wrong class")
        };
        assert_eq!(l.n_dots(), 6);
        let json = p.to_json_string();
        assert!(
            json.contains("\"bitSequence\": [1, 0, 1, 1, 1, 1]"),
            "{json}"
        );
        assert_eq!(Pattern::from_json_str(&json).unwrap(), p);
    }

    #[test]
    fn writer_format() {
        let meta = Metadata {
            description: "d \"q\"".into(),
            unit: "µm".into(),
            author: "A".into(),
            date: "2025".into(),
            margins: Margins {
                left: 10.0,
                right: 0.0,
                top: 0.25,
                bottom: 0.0,
            },
        };
        let p = Pattern::from(PeriodicLayout::new(9.0, 3, 5).unwrap().with_metadata(meta));
        let expected = "{\n    \"PeriodicPattern\": {\n        \"description\": \"d \\\"q\\\"\",\n        \"unit\": \"µm\",\n        \"leftMargin\": 10.0,\n        \"topMargin\": 0.25,\n        \"period\": 9.000000000000000,\n        \"nRows\": 3,\n        \"nCols\": 5,\n        \"author\": \"A\",\n        \"date\": \"2025\"\n    }\n}\n";
        assert_eq!(p.to_json_string(), expected);
        assert_eq!(Pattern::from_json_str(expected).unwrap(), p);
    }

    #[test]
    fn doubles_keep_their_value() {
        for v in [9.0, 0.1, 4.5, 1234.5678, 1e-7, 3.0e20, 100.1, 1.0 / 3.0] {
            let text = class_double(v);
            assert!(text.contains('.') || text.contains('e'), "{text}");
            assert_eq!(text.parse::<f64>().unwrap(), v, "{text}");
            assert_eq!(shortest_double(v).parse::<f64>().unwrap(), v);
        }
        assert_eq!(class_double(14.0), "14.000000000000000");
        assert_eq!(shortest_double(10.0), "10.0");
    }
}
