//! `docs/PROTOCOL.md` checked against the Rust protocol: every layout table (offsets,
//! sizes, types, total size and alignment, every field listed), every code, flag,
//! enumeration and constant table, the limits and iceoryx2 service settings (read from
//! the sources where they are not public), and the bytes of the worked example. A
//! number changed on either side fails here, naming the table and the row.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::{Debug, Display};
use std::mem::{align_of, offset_of, size_of};

use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::tracking::{CORRECTION_RANGE_M, Reasons, TrackingStatus};
use kfmap_map::place::RelocalizeStatus;
use kfmap_protocol::transport::{INITIAL_SLICE_LEN, MAX_CLIENTS, MAX_CLIENTS_PER_PROCESS};
use kfmap_protocol::{
    Cov2CovMode, DEFAULT_MAX_POINTS, FLAG_COVARIANCES, FLAG_FINISH_CHOSEN, FLAG_LEVELLED,
    FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN, FLAG_STAMPED, FLAG_TRACK_FROM_POSE, FLAG_TRACK_RESET,
    FLAG_VIEW_DIRS, IMU_SAMPLE_FLOATS, KIND_SLOTS, MESSAGE_LEN, NAME_LEN, PROTOCOL_VERSION,
    RequestHeader, RequestKind, ResponseHeader, STATUS_SESSIONS, ScanPayload, StatusCode,
    WireCovOptions, WirePairing, WirePlace, WireRanking, WireSessionGravity, WireTrack,
    decode_scan, imu_payload,
};

/// A file of the repository, by its path from the workspace root.
fn repo_file(path: &str) -> String {
    let full = format!("{}/../{path}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&full).unwrap_or_else(|e| panic!("cannot read {full}: {e}"))
}

// ---------------------------------------------------------------------------------
// Checks: every comparison is counted; all mismatches are reported together.

#[derive(Default)]
struct Checks {
    done: usize,
    failures: Vec<String>,
}

impl Checks {
    fn eq<T: PartialEq + Debug>(&mut self, what: impl Display, doc: T, rust: T) {
        self.done += 1;
        if doc != rust {
            self.failures.push(format!(
                "{what}: the doc says {doc:?}, the code has {rust:?}"
            ));
        }
    }

    fn truth(&mut self, what: impl Display, ok: bool) {
        self.done += 1;
        if !ok {
            self.failures.push(what.to_string());
        }
    }

    fn fail(&mut self, what: impl Display) {
        self.truth(what, false);
    }

    fn finish(self, test: &str) {
        eprintln!("{test}: {} checks", self.done);
        assert!(
            self.failures.is_empty(),
            "docs/PROTOCOL.md disagrees with the code ({} of {} checks failed):\n  {}",
            self.failures.len(),
            self.done,
            self.failures.join("\n  ")
        );
    }
}

// ---------------------------------------------------------------------------------
// The markdown: headings, tables, fenced blocks.

struct Doc {
    lines: Vec<String>,
}

/// A markdown table: lower-case column names and the cells of each row.
struct Table {
    at: String,
    columns: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Table {
    fn column(&self, name: &str) -> usize {
        self.columns
            .iter()
            .position(|c| c == name)
            .unwrap_or_else(|| panic!("{}: no column {name:?} in {:?}", self.at, self.columns))
    }

    /// The cells of column `name`, row by row.
    fn cells(&self, name: &str) -> Vec<&str> {
        let i = self.column(name);
        self.rows
            .iter()
            .map(|r| r.get(i).map_or("", String::as_str))
            .collect()
    }

    /// `(key, value)` of two columns, keys as plain text, values as numbers.
    fn numbers(&self, key: &str, value: &str, checks: &mut Checks) -> Vec<(String, f64)> {
        let keys = self.cells(key);
        let values = self.cells(value);
        let mut out = Vec::new();
        for (k, v) in keys.into_iter().zip(values) {
            match number(v) {
                Some(n) => out.push((plain(k), n)),
                None => checks.fail(format!(
                    "{}: row {:?}: {value} {v:?} is not a number",
                    self.at,
                    plain(k)
                )),
            }
        }
        out
    }
}

fn is_heading(line: &str) -> bool {
    line.starts_with('#')
}

/// Splits a table line into cells (`\|` is a literal bar).
fn cells_of(line: &str) -> Vec<String> {
    let inner = line.trim().trim_start_matches('|');
    let inner = inner.strip_suffix('|').unwrap_or(inner);
    let mut cells = vec![String::new()];
    let mut chars = inner.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' if chars.peek() == Some(&'|') => {
                cells.last_mut().expect("one cell").push('|');
                chars.next();
            }
            '|' => cells.push(String::new()),
            c => cells.last_mut().expect("one cell").push(c),
        }
    }
    cells.into_iter().map(|c| c.trim().to_string()).collect()
}

impl Doc {
    fn load() -> Self {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/PROTOCOL.md");
        let text =
            std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {path}: {e}"));
        Self {
            lines: text.lines().map(str::to_string).collect(),
        }
    }

    /// The line of the heading exactly `heading`.
    fn heading(&self, heading: &str) -> usize {
        self.lines
            .iter()
            .position(|l| l.trim() == heading)
            .unwrap_or_else(|| panic!("docs/PROTOCOL.md has no heading {heading:?}"))
    }

    /// The first table after line `start`, before the next heading.
    fn table_after(&self, start: usize) -> Table {
        let at = self.lines[start].trim().to_string();
        let section = self.lines[start + 1..]
            .iter()
            .take_while(|l| !is_heading(l));
        let rows: Vec<Vec<String>> = section
            .skip_while(|l| !l.trim_start().starts_with('|'))
            .take_while(|l| l.trim_start().starts_with('|'))
            .map(|l| cells_of(l))
            .collect();
        assert!(rows.len() >= 2, "{at}: no table under this heading");
        let columns = rows[0].iter().map(|c| c.to_lowercase()).collect();
        let is_rule = |r: &Vec<String>| r.iter().all(|c| c.chars().all(|ch| "-: ".contains(ch)));
        let rows = rows[1..].iter().filter(|r| !is_rule(r)).cloned().collect();
        Table { at, columns, rows }
    }

    fn table(&self, heading: &str) -> Table {
        self.table_after(self.heading(heading))
    }

    /// The lines of the fenced block whose info string is `info`.
    fn fenced(&self, info: &str) -> Vec<&str> {
        let open = format!("```{info}");
        let start = self
            .lines
            .iter()
            .position(|l| l.trim() == open)
            .unwrap_or_else(|| panic!("docs/PROTOCOL.md has no block {open:?}"));
        self.lines[start + 1..]
            .iter()
            .take_while(|l| l.trim() != "```")
            .map(String::as_str)
            .collect()
    }

    fn contains(&self, text: &str) -> bool {
        self.lines.iter().any(|l| l.contains(text))
    }
}

/// A cell as plain text: no code quotes, trimmed.
fn plain(cell: &str) -> String {
    cell.replace('`', "").trim().to_string()
}

/// The number a cell starts with: decimal, float or `0x` hex (`_` allowed).
fn number(cell: &str) -> Option<f64> {
    let text = plain(cell);
    parse_number(text.split_whitespace().next()?)
}

fn parse_number(token: &str) -> Option<f64> {
    let mut t = token.replace('_', "");
    for suffix in ["usize", "u64", "u32", "f64", "f32"] {
        if let Some(stripped) = t.strip_suffix(suffix) {
            t = stripped.to_string();
        }
    }
    match t.strip_prefix("0x") {
        Some(hex) => u64::from_str_radix(hex, 16).ok().map(|v| v as f64),
        None => t.parse().ok(),
    }
}

/// Evaluates `a op b op c ...` left to right (`+ - * <<`, numbers and `names`), the
/// shape of the constant expressions in the sources (`MAX_CLIENTS + 2`, `1 << 16`).
fn eval(expr: &str, names: &BTreeMap<&str, f64>) -> Option<f64> {
    let term = |t: &str| names.get(t).copied().or_else(|| parse_number(t));
    let tokens: Vec<&str> = expr.split_whitespace().collect();
    let mut value = term(tokens.first()?)?;
    for pair in tokens[1..].chunks(2) {
        let [op, t] = pair else {
            return None;
        };
        let v = term(t)?;
        value = match *op {
            "+" => value + v,
            "-" => value - v,
            "*" => value * v,
            "<<" => ((value as u64) << (v as u64)) as f64,
            _ => return None,
        };
    }
    Some(value)
}

/// A type name without module paths or spaces: `[kfmap_geometry::x::T; 16]` -> `[T;16]`.
fn bare_type(name: &str) -> String {
    let mut out = String::new();
    let mut ident = String::new();
    let mut chars = name.chars().peekable();
    while let Some(c) = chars.next() {
        if c.is_alphanumeric() || c == '_' {
            ident.push(c);
        } else if c == ':' && chars.peek() == Some(&':') {
            chars.next();
            ident.clear();
        } else {
            out.push_str(&ident);
            ident.clear();
            if !c.is_whitespace() {
                out.push(c);
            }
        }
    }
    out + &ident
}

// ---------------------------------------------------------------------------------
// The wire structs, field by field.

struct FieldInfo {
    name: &'static str,
    offset: usize,
    size: usize,
    ty: &'static str,
}

struct Layout {
    name: &'static str,
    size: usize,
    align: usize,
    fields: Vec<FieldInfo>,
}

fn field_size<S, F>(_: fn(&S) -> &F) -> usize {
    size_of::<F>()
}

fn field_type<S, F>(_: fn(&S) -> &F) -> &'static str {
    std::any::type_name::<F>()
}

/// The layout of struct `$t` with the fields listed. The list must name every field:
/// the pattern below has no `..`, so a field added to the struct and not listed here
/// stops this test from compiling.
macro_rules! layout {
    ($t:ident { $($f:ident),+ $(,)? }) => {{
        #[allow(dead_code)]
        fn every_field_is_listed(value: $t) {
            let $t { $($f: _),+ } = value;
        }
        Layout {
            name: stringify!($t),
            size: size_of::<$t>(),
            align: align_of::<$t>(),
            fields: vec![$(FieldInfo {
                name: stringify!($f),
                offset: offset_of!($t, $f),
                size: field_size(|s: &$t| &s.$f),
                ty: field_type(|s: &$t| &s.$f),
            }),+],
        }
    }};
}

fn request_header_layout() -> Layout {
    layout!(RequestHeader {
        version,
        kind,
        request_id,
        client_node,
        pose,
        point_count,
        flags,
        k,
        mode,
        radius,
        max_pair_dist,
        max_iterations,
        max_correction,
        keyframe_or_scan_id,
        imu_t0,
        expected_inlier_ratio,
        keyframes,
        stamp,
    })
}

fn wire_layouts() -> Vec<Layout> {
    vec![
        request_header_layout(),
        layout!(ResponseHeader {
            version,
            status,
            request_id,
            detail,
            message_len,
            active_len,
            active,
            server_us,
            pose,
            covariance,
            fitness,
            iterations,
            converged,
            tracking,
            reasons,
            registrations,
            degenerate,
            constraint,
            pose_correction,
            relocalization,
            candidates,
            place_scores,
            tight_fitness,
            has_gravity,
            gravity_members,
            gravity,
            roll_pitch,
            correction,
            gravity_inliers,
            gravity_compensated,
            gravity_pending,
            gravity_skipped,
            bias_observable,
            gravity_reserved,
            gravity_spread_deg,
            accel_bias,
            accel_bias_sigma,
            map_keyframes,
            map_points,
            uptime_s,
            counts,
            p50_us,
            p99_us,
            sessions,
            in_flight,
            map_name_len,
            map_name,
            message,
            message_reserved,
            session_gravity,
            scan_covariance,
            relocalize_ranking,
            track,
        }),
        layout!(WireTrack {
            predicted,
            t,
            explained,
            slide_loss,
            max_correction,
            hypotheses,
            known,
            imu_refused,
            reserved,
        }),
        layout!(WireRanking {
            keep_ratio,
            separation_m,
            separation_deg,
            ambiguity_margin,
            distinct_m,
            distinct_deg,
        }),
        layout!(WireCovOptions {
            k_correspondences,
            min_correspondences,
            center,
            reserved,
            max_distance,
            lambda,
            max_plane_deviation,
        }),
        layout!(WireSessionGravity {
            client_node,
            members,
            compensated,
            pending,
            skipped,
            inliers,
            has_gravity,
            bias_observable,
            busy,
            roll_pitch,
            spread_deg,
            accel_bias,
            gravity,
        }),
        layout!(WirePairing {
            query,
            local_index,
            keyframe,
            point,
            dist_sq,
            information,
        }),
        layout!(WirePlace {
            translation,
            rotation,
            score,
            rank,
        }),
    ]
}

/// A struct heading: "### `Name` (size N, align M)".
struct StructHeading {
    line: usize,
    size: Option<f64>,
    align: Option<f64>,
}

fn struct_headings(doc: &Doc) -> BTreeMap<String, StructHeading> {
    let after = |text: &str, word: &str| {
        let rest = &text[text.find(word)? + word.len()..];
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        parse_number(&digits)
    };
    let mut found = BTreeMap::new();
    for (line, text) in doc.lines.iter().enumerate() {
        let Some(rest) = text.strip_prefix("### `") else {
            continue;
        };
        let Some((name, tail)) = rest.split_once('`') else {
            continue;
        };
        if !tail.contains("size") {
            continue;
        }
        let heading = StructHeading {
            line,
            size: after(tail, "size "),
            align: after(tail, "align "),
        };
        found.insert(name.to_string(), heading);
    }
    found
}

const PADDING: &str = "(padding)";

#[test]
fn struct_layouts_match_the_doc() {
    let doc = Doc::load();
    let layouts = wire_layouts();
    let headings = struct_headings(&doc);
    let mut c = Checks::default();
    c.eq(
        "structs with a layout table",
        headings.keys().cloned().collect::<BTreeSet<_>>(),
        layouts.iter().map(|l| l.name.to_string()).collect(),
    );
    for layout in &layouts {
        let name = layout.name;
        let Some(heading) = headings.get(name) else {
            continue;
        };
        c.eq(
            format!("{name}: total size"),
            heading.size,
            Some(layout.size as f64),
        );
        c.eq(
            format!("{name}: alignment"),
            heading.align,
            Some(layout.align as f64),
        );
        let table = doc.table_after(heading.line);
        let fields = table.cells("field");
        let offsets = table.cells("offset");
        let sizes = table.cells("size");
        let types = table.cells("type");
        let mut end = 0;
        let mut listed = Vec::new();
        for (i, field) in fields.iter().enumerate() {
            let field = plain(field);
            let (Some(offset), Some(size)) = (number(offsets[i]), number(sizes[i])) else {
                c.fail(format!("{name}.{field}: offset or size is not a number"));
                continue;
            };
            let (offset, size) = (offset as usize, size as usize);
            c.eq(
                format!("{name}.{field}: starts where the row before ends (no gap, no overlap)"),
                offset,
                end,
            );
            end = offset + size;
            if field == PADDING {
                c.truth(
                    format!("{name}: padding at {offset} is {size} bytes, less than the alignment"),
                    size > 0 && size < layout.align,
                );
                continue;
            }
            listed.push(field.clone());
            let Some(f) = layout.fields.iter().find(|f| f.name == field) else {
                c.fail(format!("{name}.{field}: documented, but no such field"));
                continue;
            };
            c.eq(format!("{name}.{field}: offset"), offset, f.offset);
            c.eq(format!("{name}.{field}: size"), size, f.size);
            c.eq(
                format!("{name}.{field}: type"),
                bare_type(&plain(types[i])),
                bare_type(f.ty),
            );
        }
        c.eq(
            format!("{name}: the rows end at the struct's size"),
            end,
            layout.size,
        );
        c.eq(
            format!("{name}: every field documented once, in order"),
            listed,
            layout.fields.iter().map(|f| f.name.to_string()).collect(),
        );
    }
    c.finish("struct layouts");
}

// ---------------------------------------------------------------------------------
// Codes, flags, enumerations, constants.

/// Compares a documented `name -> number` table with the code's, both ways.
fn same_entries(
    c: &mut Checks,
    table: &Table,
    (key, value): (&str, &str),
    rust: Vec<(String, f64)>,
) {
    let doc = table.numbers(key, value, c);
    let what = table.at.as_str();
    let doc_names: Vec<&String> = doc.iter().map(|(n, _)| n).collect();
    let unique: BTreeSet<&String> = doc_names.iter().copied().collect();
    c.eq(
        format!("{what}: rows named once each"),
        unique.len(),
        doc_names.len(),
    );
    let doc: BTreeMap<String, f64> = doc.into_iter().collect();
    let rust: BTreeMap<String, f64> = rust.into_iter().collect();
    c.eq(
        format!("{what}: the names listed"),
        doc.keys().collect::<Vec<_>>(),
        rust.keys().collect::<Vec<_>>(),
    );
    for (name, value) in &rust {
        if let Some(documented) = doc.get(name) {
            c.eq(format!("{what}: {name}"), *documented, *value);
        }
    }
}

/// Compares a documented `name -> lower-case name` column with the code's.
fn same_names(c: &mut Checks, table: &Table, key: &str, column: &str, rust: &[(String, &str)]) {
    let keys = table.cells(key);
    let names = table.cells(column);
    for (k, n) in keys.iter().zip(names) {
        let k = plain(k);
        if let Some((_, name)) = rust.iter().find(|(r, _)| *r == k) {
            c.eq(
                format!("{}: {k}: {column}", table.at),
                plain(n),
                name.to_string(),
            );
        }
    }
}

#[test]
fn request_kinds_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("## Request kinds");
    let rust: Vec<(String, f64)> = RequestKind::ALL
        .iter()
        .map(|k| (format!("{k:?}"), *k as u32 as f64))
        .collect();
    same_entries(&mut c, &table, ("kind", "code"), rust);
    let names: Vec<(String, &str)> = RequestKind::ALL
        .iter()
        .map(|k| (format!("{k:?}"), k.name()))
        .collect();
    same_names(&mut c, &table, "kind", "name", &names);
    for kind in RequestKind::ALL {
        c.truth(
            format!("kind {kind:?} has a slot in the status counts (KIND_SLOTS)"),
            (kind as usize) < KIND_SLOTS,
        );
    }
    c.finish("request kinds");
}

#[test]
fn status_codes_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("## Status codes");
    // Every code the client library maps to itself (unknown codes read as Internal).
    let rust: Vec<(String, f64)> = (0..1024u32)
        .map(|code| (code, StatusCode::from_code(code)))
        .filter(|(code, s)| *s as u32 == *code)
        .map(|(code, s)| (format!("{s:?}"), code as f64))
        .collect();
    same_entries(&mut c, &table, ("status", "code"), rust);
    c.finish("status codes");
}

#[test]
fn flags_match_the_doc_and_the_decoder() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("## Flags");
    // Malformed cells are reported by same_entries below.
    let documented = table.numbers("flag", "value", &mut Checks::default());
    let rust = [
        ("FLAG_VIEW_DIRS", FLAG_VIEW_DIRS),
        ("FLAG_COVARIANCES", FLAG_COVARIANCES),
        ("FLAG_STAMPED", FLAG_STAMPED),
        ("FLAG_LEVELLED", FLAG_LEVELLED),
        ("FLAG_PLACES_ONLY", FLAG_PLACES_ONLY),
        ("FLAG_SCORE_CHOSEN", FLAG_SCORE_CHOSEN),
        ("FLAG_FINISH_CHOSEN", FLAG_FINISH_CHOSEN),
        ("FLAG_TRACK_RESET", FLAG_TRACK_RESET),
        ("FLAG_TRACK_FROM_POSE", FLAG_TRACK_FROM_POSE),
    ];
    let documented_bits = documented.iter().fold(0u32, |a, (_, v)| a | *v as u32);
    same_entries(
        &mut c,
        &table,
        ("flag", "value"),
        rust.iter()
            .map(|(n, v)| (n.to_string(), *v as f64))
            .collect(),
    );
    // The scan decoder accepts exactly the documented bits (one point, whatever
    // payload length the bit asks for).
    for bit in 0..32 {
        let header = RequestHeader {
            kind: RequestKind::Nearest as u32,
            point_count: 1,
            flags: 1 << bit,
            ..Default::default()
        };
        let accepted = [3, 6, 9, 12]
            .iter()
            .any(|&len| decode_scan(&header, &vec![0.0; len], 10).is_ok());
        c.eq(
            format!("flag bit {:#x} accepted by decode_scan", 1u32 << bit),
            documented_bits & (1 << bit) != 0,
            accepted,
        );
    }
    c.finish("flags");
}

#[test]
fn enumerated_fields_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();

    let modes: Vec<Cov2CovMode> = (0..256).filter_map(Cov2CovMode::from_code).collect();
    let table = doc.table("### Cov2cov modes");
    same_entries(
        &mut c,
        &table,
        ("mode", "code"),
        modes
            .iter()
            .map(|m| (format!("{m:?}"), *m as u32 as f64))
            .collect(),
    );
    let names: Vec<_> = modes.iter().map(|m| (format!("{m:?}"), m.name())).collect();
    same_names(&mut c, &table, "mode", "config name", &names);

    let table = doc.table("### Tracking status");
    same_entries(
        &mut c,
        &table,
        ("status", "code"),
        TrackingStatus::ALL
            .iter()
            .map(|s| (format!("{s:?}"), *s as u32 as f64))
            .collect(),
    );
    let names: Vec<_> = TrackingStatus::ALL
        .iter()
        .map(|s| (format!("{s:?}"), s.name()))
        .collect();
    same_names(&mut c, &table, "status", "name", &names);

    let table = doc.table("### Tracking reasons");
    let reasons: Vec<(String, f64)> = (0..32)
        .filter_map(|bit| {
            let names = Reasons(1 << bit).names();
            names.first().map(|n| (n.to_string(), (1u64 << bit) as f64))
        })
        .collect();
    same_entries(&mut c, &table, ("reason", "bit value"), reasons);

    let table = doc.table("### Relocalization status");
    same_entries(
        &mut c,
        &table,
        ("status", "code"),
        RelocalizeStatus::ALL
            .iter()
            .map(|s| (format!("{s:?}"), *s as u32 as f64))
            .collect(),
    );
    let names: Vec<_> = RelocalizeStatus::ALL
        .iter()
        .map(|s| (format!("{s:?}"), s.name()))
        .collect();
    same_names(&mut c, &table, "status", "name", &names);
    c.finish("enumerated fields");
}

/// The public constants the doc lists, by path.
fn constants() -> Vec<(&'static str, f64)> {
    vec![
        ("kfmap_protocol::PROTOCOL_VERSION", PROTOCOL_VERSION as f64),
        (
            "kfmap_protocol::DEFAULT_MAX_POINTS",
            DEFAULT_MAX_POINTS as f64,
        ),
        (
            "kfmap_protocol::IMU_SAMPLE_FLOATS",
            IMU_SAMPLE_FLOATS as f64,
        ),
        ("kfmap_protocol::MESSAGE_LEN", MESSAGE_LEN as f64),
        ("kfmap_protocol::NAME_LEN", NAME_LEN as f64),
        ("kfmap_protocol::KIND_SLOTS", KIND_SLOTS as f64),
        ("kfmap_protocol::STATUS_SESSIONS", STATUS_SESSIONS as f64),
        ("kfmap_protocol::transport::MAX_CLIENTS", MAX_CLIENTS as f64),
        (
            "kfmap_protocol::transport::MAX_CLIENTS_PER_PROCESS",
            MAX_CLIENTS_PER_PROCESS as f64,
        ),
        (
            "kfmap_protocol::transport::INITIAL_SLICE_LEN",
            INITIAL_SLICE_LEN as f64,
        ),
        (
            "kfmap_geometry::gravity::MAX_MEMBERS",
            kfmap_geometry::gravity::MAX_MEMBERS as f64,
        ),
        (
            "kfmap_geometry::tracking::CORRECTION_RANGE_M",
            CORRECTION_RANGE_M,
        ),
    ]
}

/// The constants by their last path segment, for expressions in the sources.
fn constant_names() -> BTreeMap<&'static str, f64> {
    constants()
        .into_iter()
        .map(|(path, v)| (path.rsplit("::").next().expect("a name"), v))
        .collect()
}

#[test]
fn constants_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("## Constants");
    same_entries(
        &mut c,
        &table,
        ("constant", "value"),
        constants()
            .into_iter()
            .map(|(n, v)| (n.to_string(), v))
            .collect(),
    );
    for text in [
        format!("**protocol version {PROTOCOL_VERSION}**"),
        format!("`PROTOCOL_VERSION` is **{PROTOCOL_VERSION}**"),
    ] {
        c.truth(
            format!("the doc says {text:?} (the version in its prose)"),
            doc.contains(&text),
        );
    }
    c.finish("constants");
}

// ---------------------------------------------------------------------------------
// Limits and service settings: values the server keeps outside this crate's public
// API, read from the sources and config/server.toml.

/// The value of `key` in section `[section]` of a TOML file's text.
fn toml_value(text: &str, section: &str, key: &str) -> Option<f64> {
    let header = format!("[{section}]");
    let mut inside = false;
    for line in text.lines().map(str::trim) {
        if line.starts_with('[') {
            inside = line == header;
        } else if inside
            && let Some((k, v)) = line.split_once('=')
            && k.trim() == key
        {
            return parse_number(v.split('#').next().unwrap_or("").trim());
        }
    }
    None
}

/// The value of `const NAME: T = EXPR;` in a source file.
fn source_const(text: &str, name: &str) -> Option<f64> {
    let at = text.find(&format!("const {name}:"))?;
    let statement = &text[at..at + text[at..].find(';')?];
    eval(statement.split_once('=')?.1, &constant_names())
}

/// The value a limit's source gives, or why it cannot be read.
fn limit_source(source: &str) -> Result<f64, String> {
    let crates = [
        "kfmap_geometry::",
        "kfmap_map::",
        "kfmap_graph::",
        "kfmap_protocol::",
    ];
    if crates.iter().any(|c| source.starts_with(c)) {
        return constants()
            .into_iter()
            .find(|(n, _)| *n == source)
            .map(|(_, v)| v)
            .ok_or_else(|| format!("{source} is not among this test's constants()"));
    }
    let (file, rest) = source
        .split_once(' ')
        .ok_or_else(|| format!("source {source:?} is not \"FILE NAME\""))?;
    let text = repo_file(file);
    let value = if file.ends_with(".toml") {
        let (section, key) = rest
            .trim()
            .strip_prefix('[')
            .and_then(|r| r.split_once(']'))
            .ok_or_else(|| format!("source {source:?} is not \"FILE [section] key\""))?;
        toml_value(&text, section, key.trim())
    } else {
        source_const(&text, rest.trim())
    };
    value.ok_or_else(|| format!("{source}: not found"))
}

#[test]
fn limits_match_the_sources() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("## Limits");
    let limits = table.cells("limit");
    let values = table.cells("value");
    for (i, source) in table.cells("source").into_iter().enumerate() {
        let what = format!("limit {:?} ({})", plain(limits[i]), plain(source));
        match limit_source(&plain(source)) {
            Ok(value) => c.eq(what, number(values[i]), Some(value)),
            Err(e) => c.fail(format!("{what}: {e}")),
        }
    }
    c.eq(
        "server.toml max-points-per-request is the library's DEFAULT_MAX_POINTS",
        toml_value(
            &repo_file("config/server.toml"),
            "server",
            "max-points-per-request",
        ),
        Some(DEFAULT_MAX_POINTS as f64),
    );
    c.finish("limits");
}

/// Text without whitespace, to find code however it is wrapped.
fn squeeze(text: &str) -> String {
    text.chars().filter(|c| !c.is_whitespace()).collect()
}

/// The body of `fn name` in a source text (to the first line that is just `}`).
fn function_body<'a>(text: &'a str, name: &str) -> &'a str {
    let start = text
        .find(&format!("fn {name}("))
        .unwrap_or_else(|| panic!("no fn {name} in the source"));
    let end = text[start..]
        .find("\n}\n")
        .map_or(text.len(), |e| start + e);
    &text[start..end]
}

#[test]
fn service_settings_match_the_sources() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let table = doc.table("### Service settings a client must match");
    let codes = table.cells("code");
    let values = table.cells("value");
    let settings = table.cells("setting");
    let mut documented = BTreeSet::new();
    for (i, file) in table.cells("file").into_iter().enumerate() {
        let (file, code) = (plain(file), plain(codes[i]));
        let what = format!("setting {:?}", plain(settings[i]));
        c.truth(
            format!("{what}: {file} calls {code}"),
            squeeze(&repo_file(&file)).contains(&squeeze(&code)),
        );
        let argument = code
            .split_once('(')
            .and_then(|(_, a)| a.rsplit_once(')'))
            .map(|(a, _)| a);
        let value = argument.and_then(|a| eval(a, &constant_names()));
        c.eq(format!("{what}: value of {code}"), number(values[i]), value);
        if file.ends_with("transport.rs") {
            documented.insert(squeeze(&code));
        }
    }
    // Every limit the services are built with is in the table.
    let transport = repo_file("protocol/src/transport.rs");
    for function in ["open_rpc", "open_event"] {
        for line in function_body(&transport, function).lines() {
            let line = line.trim();
            if line.starts_with(".max_") {
                c.truth(
                    format!("{function}'s {line} is documented"),
                    documented.contains(&squeeze(line)),
                );
            }
        }
    }
    c.finish("service settings");
}

/// The iceoryx2 type name each wire struct declares (`#[type_name(...)]` in wire.rs).
fn declared_type_names() -> BTreeMap<String, String> {
    let wire = repo_file("protocol/src/wire.rs");
    let mut names = BTreeMap::new();
    let mut pending: Option<String> = None;
    for line in wire.lines().map(str::trim) {
        if let Some(rest) = line.strip_prefix("#[type_name(\"") {
            pending = rest.split('"').next().map(str::to_string);
        } else if let Some(rest) = line.strip_prefix("pub struct ")
            && let Some(type_name) = pending.take()
        {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            names.insert(name, type_name);
        }
    }
    names
}

#[test]
fn payload_types_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let declared = declared_type_names();
    let table = doc.table("### Payload types iceoryx2 checks");
    let rust = [
        (
            "f32",
            "f32".to_string(),
            size_of::<f32>(),
            align_of::<f32>(),
        ),
        (
            "RequestHeader",
            declared["RequestHeader"].clone(),
            size_of::<RequestHeader>(),
            align_of::<RequestHeader>(),
        ),
        (
            "WirePairing",
            declared["WirePairing"].clone(),
            size_of::<WirePairing>(),
            align_of::<WirePairing>(),
        ),
        (
            "ResponseHeader",
            declared["ResponseHeader"].clone(),
            size_of::<ResponseHeader>(),
            align_of::<ResponseHeader>(),
        ),
    ];
    c.eq(
        "f32's iceoryx2 type name is Rust's",
        std::any::type_name::<f32>(),
        "f32",
    );
    let types = table.cells("rust type");
    let names = table.cells("iceoryx2 type name");
    let sizes = table.cells("size");
    let aligns = table.cells("align");
    c.eq(
        "payload types: the Rust types listed, in role order",
        types.iter().map(|t| plain(t)).collect::<Vec<_>>(),
        rust.iter().map(|r| r.0.to_string()).collect(),
    );
    for (i, ty) in types.iter().enumerate() {
        let ty = plain(ty);
        let Some((_, type_name, size, align)) = rust.iter().find(|r| r.0 == ty) else {
            continue;
        };
        c.eq(
            format!("{ty}: iceoryx2 type name"),
            plain(names[i]),
            type_name.clone(),
        );
        c.eq(format!("{ty}: size"), number(sizes[i]), Some(*size as f64));
        c.eq(
            format!("{ty}: align"),
            number(aligns[i]),
            Some(*align as f64),
        );
    }
    let session = format!("type name `{}`", declared["WireSessionGravity"]);
    c.truth(
        format!("the doc names WireSessionGravity's {session}"),
        doc.contains(&session),
    );
    // The service carries these types in these roles.
    c.truth(
        "transport::Rpc is [f32] + RequestHeader -> [WirePairing] + ResponseHeader",
        squeeze(&repo_file("protocol/src/transport.rs")).contains(&squeeze(
            "RpcFactory<Transport, [f32], RequestHeader, [WirePairing], ResponseHeader>",
        )),
    );
    c.finish("payload types");
}

#[test]
fn payload_layouts_match_the_doc() {
    let doc = Doc::load();
    let mut c = Checks::default();

    // Scan arrays: floats per point, measured on a one-point payload.
    let table = doc.table("### Scan payload");
    let point = [[1.0f32, 2.0, 3.0]];
    let cov = [[1.0f32, 0.0, 0.0, 1.0, 0.0, 1.0]];
    let scan = |views: bool, covs: bool| ScanPayload {
        points: &point,
        view_dirs: views.then_some(&point[..]),
        covariances: covs.then_some(&cov[..]),
    };
    let flags_of = |s: ScanPayload| {
        let mut h = RequestHeader::default();
        s.encode(&mut h);
        h.flags
    };
    let base = scan(false, false).float_len();
    let rust = [
        ("points", base, "always".to_string()),
        (
            "view directions",
            scan(true, false).float_len() - base,
            format!("FLAG_VIEW_DIRS={}", flags_of(scan(true, false))),
        ),
        (
            "covariances",
            scan(false, true).float_len() - base,
            format!("FLAG_COVARIANCES={}", flags_of(scan(false, true))),
        ),
    ];
    let arrays = table.cells("array");
    let floats = table.cells("floats per point");
    let when = table.cells("present when");
    c.eq(
        "scan payload: the arrays, in order",
        arrays.iter().map(|a| plain(a)).collect::<Vec<_>>(),
        rust.iter().map(|r| r.0.to_string()).collect(),
    );
    let flag_values = [
        ("FLAG_VIEW_DIRS", FLAG_VIEW_DIRS),
        ("FLAG_COVARIANCES", FLAG_COVARIANCES),
    ];
    for (i, (array, per_point, flag)) in rust.iter().enumerate() {
        let Some(&cell) = floats.get(i) else {
            continue;
        };
        c.eq(
            format!("scan payload: {array}: floats per point"),
            number(cell),
            Some(*per_point as f64),
        );
        // "FLAG_X" in the doc, with the value the encoder sets for that array.
        let documented = plain(when[i]);
        let documented = flag_values
            .iter()
            .find(|(n, _)| *n == documented)
            .map_or(documented.clone(), |(n, v)| format!("{n}={v}"));
        c.eq(
            format!("scan payload: {array}: present when"),
            documented,
            flag.clone(),
        );
    }

    // IMU sample: one row per float, in the encoder's order.
    let table = doc.table("### IMU sample");
    let indices = table.cells("float");
    c.eq("IMU sample: rows", indices.len(), IMU_SAMPLE_FLOATS);
    for (i, cell) in indices.iter().enumerate() {
        c.eq(
            format!("IMU sample: row {i}: float index"),
            number(cell),
            Some(i as f64),
        );
    }
    let sample = ImuSample {
        t: 101.0,
        acc: [1.0, 2.0, 3.0],
        gyro: [4.0, 5.0, 6.0],
    };
    let encoded = imu_payload(&[sample], 100.0);
    c.eq(
        "IMU sample: encoded floats",
        encoded.len(),
        IMU_SAMPLE_FLOATS,
    );
    // What each float of the encoded sample is, as the doc's meaning must say it.
    let meanings = table.cells("meaning");
    let expected: [(f32, &[&str]); 7] = [
        (1.0, &["time", "imu_t0"]),
        (1.0, &["force", "x"]),
        (2.0, &["force", "y"]),
        (3.0, &["force", "z"]),
        (4.0, &["rate", "x"]),
        (5.0, &["rate", "y"]),
        (6.0, &["rate", "z"]),
    ];
    for (i, (value, words)) in expected.iter().enumerate() {
        c.eq(
            format!("IMU sample: float {i} encodes"),
            encoded.get(i),
            Some(value),
        );
        let meaning = meanings.get(i).map_or(String::new(), |m| m.to_lowercase());
        c.truth(
            format!("IMU sample: float {i}'s meaning mentions {words:?}"),
            words.iter().all(|w| meaning.contains(w)),
        );
    }
    c.finish("payload layouts");
}

// ---------------------------------------------------------------------------------
// The worked example.

/// `(offset, bytes, note)` of a hexdump block: "0xOFFSET  bytes...  # note".
fn hexdump(lines: &[&str], c: &mut Checks, what: &str) -> Vec<(usize, Vec<u8>, String)> {
    let mut out = Vec::new();
    for line in lines {
        let (data, note) = line.split_once('#').unwrap_or((line, ""));
        let mut tokens = data.split_whitespace();
        let Some(offset) = tokens
            .next()
            .and_then(|t| usize::from_str_radix(t.trim_start_matches("0x"), 16).ok())
        else {
            c.fail(format!("{what}: line {line:?} has no hex offset"));
            continue;
        };
        let bytes: Option<Vec<u8>> = tokens.map(|t| u8::from_str_radix(t, 16).ok()).collect();
        match bytes {
            Some(bytes) => out.push((offset, bytes, note.trim().to_string())),
            None => c.fail(format!(
                "{what}: line {line:?} has a token that is not a byte"
            )),
        }
    }
    out
}

/// Compares a hexdump with the bytes it shows, line by line.
fn check_dump(c: &mut Checks, what: &str, dump: &[(usize, Vec<u8>, String)], bytes: &[u8]) {
    let mut end = 0;
    for (offset, shown, _) in dump {
        c.eq(
            format!("{what}: line at {offset:#06x} follows the one before"),
            *offset,
            end,
        );
        let actual = bytes.get(*offset..offset + shown.len());
        c.eq(
            format!("{what}: bytes at {offset:#06x}"),
            Some(shown.as_slice()),
            actual,
        );
        end = offset + shown.len();
    }
    c.eq(format!("{what}: length"), end, bytes.len());
}

#[cfg(target_endian = "little")]
#[test]
fn worked_example_bytes_match_the_encoder() {
    let doc = Doc::load();
    let mut c = Checks::default();
    let points = [[1.0f32, 0.5, -2.0], [10.0, 0.0, 0.25]];
    let mut header = RequestHeader {
        kind: RequestKind::Nearest as u32,
        request_id: 1,
        client_node: [0x0123_4567_89ab_cdef, 0x0fed_cba9_8765_4321],
        pose: [2.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        k: 4,
        ..Default::default()
    };
    let payload = ScanPayload {
        points: &points,
        view_dirs: None,
        covariances: None,
    }
    .encode(&mut header);
    // The header as it lies in shared memory. It has no padding: the layout test
    // checks that its fields cover all of its bytes.
    let header_bytes: Vec<u8> = {
        let ptr = (&header as *const RequestHeader).cast::<u8>();
        // SAFETY: a live, fully initialized value without padding bytes, read as
        // size_of::<RequestHeader>() bytes while it is borrowed.
        unsafe { std::slice::from_raw_parts(ptr, size_of::<RequestHeader>()) }.to_vec()
    };
    let dump = hexdump(
        &doc.fenced("hexdump RequestHeader"),
        &mut c,
        "example header",
    );
    check_dump(&mut c, "example header", &dump, &header_bytes);
    // Each line's note starts with the field it shows.
    let layout = request_header_layout();
    for (offset, shown, note) in &dump {
        let named = note.split([' ', '[']).next().unwrap_or("");
        let field = layout
            .fields
            .iter()
            .find(|f| f.offset <= *offset && offset + shown.len() <= f.offset + f.size);
        c.eq(
            format!("example header: the note at {offset:#06x} names its field"),
            named,
            field.map_or("(no single field)", |f| f.name),
        );
    }
    let payload_bytes: Vec<u8> = payload.iter().flat_map(|v| v.to_le_bytes()).collect();
    let dump = hexdump(&doc.fenced("hexdump payload"), &mut c, "example payload");
    check_dump(&mut c, "example payload", &dump, &payload_bytes);
    c.eq(
        "the example decodes as the server would",
        decode_scan(&header, &payload, DEFAULT_MAX_POINTS)
            .map(|d| d.points.to_vec())
            .ok(),
        Some(points.to_vec()),
    );
    c.finish("worked example");
}
