//! PCD v0.5-0.7 (the Point Cloud Library's format): `ascii`, `binary` and
//! `binary_compressed` data, any field order, F/I/U fields of 1-8 bytes.

use std::path::Path;

use super::error::{IoError, Location};
use super::fields::{Assembler, Scalar, output_value, push_ascii_row, push_binary_row};
use super::lzf;
use crate::cloud::PointCloud;

/// Values one point may carry over all fields (the sum of COUNT).
pub const MAX_SCALARS_PER_POINT: usize = 4096;
/// The storage mode of a PCD file's data section.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PcdData {
    /// Whitespace-separated text, one point per line.
    Ascii,
    /// Packed little-endian records.
    Binary,
    /// LZF-compressed, field-major (all x, then all y, ...).
    BinaryCompressed,
}

struct Field {
    name: String,
    ty: Scalar,
    count: usize,
}

struct Header {
    fields: Vec<Field>,
    points: usize,
    data: PcdData,
    /// Byte offset where the data section starts.
    data_start: usize,
    /// Line number of the DATA line, for text errors.
    data_line: usize,
}

fn parse_scalar(ty: &str, size: usize) -> Option<Scalar> {
    Some(match (ty, size) {
        ("F", 4) => Scalar::F32,
        ("F", 8) => Scalar::F64,
        ("I", 1) => Scalar::I8,
        ("I", 2) => Scalar::I16,
        ("I", 4) => Scalar::I32,
        ("I", 8) => Scalar::I64,
        ("U", 1) => Scalar::U8,
        ("U", 2) => Scalar::U16,
        ("U", 4) => Scalar::U32,
        ("U", 8) => Scalar::U64,
        _ => return None,
    })
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<Header, IoError> {
    let bad = |line: usize, reason: String| IoError::malformed(path, Location::Line(line), reason);
    let (mut names, mut sizes, mut types, mut counts) = (None, None, None, None);
    let (mut width, mut height, mut points) = (None::<usize>, None::<usize>, None::<usize>);
    let mut offset = 0usize;
    let mut line_no = 0usize;
    while offset < bytes.len() {
        let end = bytes[offset..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |p| offset + p);
        let line = String::from_utf8_lossy(&bytes[offset..end]);
        line_no += 1;
        offset = (end + 1).min(bytes.len());
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut words = line.split_whitespace();
        let key = words.next().unwrap_or_default().to_ascii_uppercase();
        let rest: Vec<&str> = words.collect();
        let one_number = |what: &str| -> Result<usize, IoError> {
            rest.first().and_then(|w| w.parse().ok()).ok_or_else(|| {
                bad(
                    line_no,
                    format!(
                        "{what} needs a non-negative integer, got '{}'",
                        rest.join(" ")
                    ),
                )
            })
        };
        let integers = |what: &str| -> Result<Vec<usize>, IoError> {
            rest.iter()
                .map(|w| w.parse::<usize>())
                .collect::<Result<Vec<_>, _>>()
                .map_err(|_| {
                    bad(
                        line_no,
                        format!("{what} has a non-integer entry: '{}'", rest.join(" ")),
                    )
                })
        };
        match key.as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" | "COLUMNS" => {
                names = Some(rest.iter().map(|s| s.to_string()).collect::<Vec<_>>())
            }
            "SIZE" => sizes = Some(integers("SIZE")?),
            "TYPE" => {
                types = Some(
                    rest.iter()
                        .map(|s| s.to_ascii_uppercase())
                        .collect::<Vec<_>>(),
                )
            }
            "COUNT" => counts = Some(integers("COUNT")?),
            "WIDTH" => width = Some(one_number("WIDTH")?),
            "HEIGHT" => height = Some(one_number("HEIGHT")?),
            "POINTS" => points = Some(one_number("POINTS")?),
            "DATA" => {
                let data = match rest.first().map(|s| s.to_ascii_lowercase()).as_deref() {
                    Some("ascii") => PcdData::Ascii,
                    Some("binary") => PcdData::Binary,
                    Some("binary_compressed") => PcdData::BinaryCompressed,
                    other => {
                        return Err(bad(
                            line_no,
                            format!(
                                "unknown DATA mode {other:?}; expected ascii, binary or binary_compressed"
                            ),
                        ));
                    }
                };
                let names =
                    names.ok_or_else(|| bad(line_no, "header has no FIELDS line".into()))?;
                let n = names.len();
                let sizes = sizes.unwrap_or_else(|| vec![4; n]);
                let types = types.unwrap_or_else(|| vec!["F".into(); n]);
                let counts = counts.unwrap_or_else(|| vec![1; n]);
                if sizes.len() != n || types.len() != n || counts.len() != n {
                    return Err(bad(
                        line_no,
                        format!(
                            "FIELDS has {n} entries but SIZE {}, TYPE {}, COUNT {}",
                            sizes.len(),
                            types.len(),
                            counts.len()
                        ),
                    ));
                }
                // Each scalar costs a name and a slot per point: bound them before any
                // allocation (the widest PCL descriptor, VFH, has 308).
                let scalars = counts
                    .iter()
                    .try_fold(0usize, |sum, c| sum.checked_add(*c))
                    .filter(|s| *s <= MAX_SCALARS_PER_POINT);
                if scalars.is_none() {
                    return Err(bad(
                        line_no,
                        format!(
                            "COUNT {counts:?} adds up to more than {MAX_SCALARS_PER_POINT} values per point"
                        ),
                    ));
                }
                let mut fields = Vec::with_capacity(n);
                for i in 0..n {
                    let ty = parse_scalar(&types[i], sizes[i]).ok_or_else(|| {
                        bad(
                            line_no,
                            format!(
                                "field '{}' has unsupported TYPE {} SIZE {}",
                                names[i], types[i], sizes[i]
                            ),
                        )
                    })?;
                    fields.push(Field {
                        name: names[i].clone(),
                        ty,
                        count: counts[i],
                    });
                }
                let points = match (points, width, height) {
                    (Some(p), _, _) => p,
                    (None, Some(w), h) => w.checked_mul(h.unwrap_or(1)).ok_or_else(|| {
                        bad(line_no, "WIDTH x HEIGHT overflows a point count".into())
                    })?,
                    _ => return Err(bad(line_no, "header has neither POINTS nor WIDTH".into())),
                };
                return Ok(Header {
                    fields,
                    points,
                    data,
                    data_start: offset,
                    data_line: line_no,
                });
            }
            other => return Err(bad(line_no, format!("unknown header keyword '{other}'"))),
        }
    }
    Err(IoError::malformed(
        path,
        Location::Line(line_no),
        "header ends without a DATA line",
    ))
}

/// One name per scalar: a field with COUNT > 1 expands to `name`, `name_1`, ...
fn scalar_names(fields: &[Field]) -> Vec<String> {
    fields
        .iter()
        .flat_map(|f| {
            (0..f.count).map(move |c| {
                if c == 0 {
                    f.name.clone()
                } else {
                    format!("{}_{c}", f.name)
                }
            })
        })
        .collect()
}

/// Reads a PCD file from its bytes. Returns the cloud, the data mode and the field
/// names as written in the header.
pub fn read_pcd(path: &Path, bytes: &[u8]) -> Result<(PointCloud, PcdData, Vec<String>), IoError> {
    let header = parse_header(path, bytes)?;
    let names = scalar_names(&header.fields);
    let types: Vec<Scalar> = header
        .fields
        .iter()
        .flat_map(|f| std::iter::repeat_n(f.ty, f.count))
        .collect();
    let body = &bytes[header.data_start..];
    // Capacity from the file size, not the header: a lying header must not allocate.
    let mut asm = Assembler::new(&names, header.points.min(body.len()))
        .map_err(|reason| IoError::malformed(path, Location::Line(header.data_line), reason))?;
    let record: usize = types.iter().map(|t| t.size()).sum();
    let total_bytes = record.checked_mul(header.points).ok_or_else(|| {
        IoError::malformed(
            path,
            Location::Line(header.data_line),
            format!("POINTS {} is impossibly large", header.points),
        )
    })?;
    match header.data {
        PcdData::Ascii => read_ascii_body(path, body, &header, names.len(), &mut asm)?,
        PcdData::Binary => {
            let need = total_bytes;
            if body.len() < need {
                return Err(IoError::malformed(
                    path,
                    Location::Byte((header.data_start + body.len()) as u64),
                    format!(
                        "binary data truncated: {} points of {record} bytes need {need} bytes, file has {}",
                        header.points,
                        body.len()
                    ),
                ));
            }
            let offsets = prefix_offsets(&types);
            for rec in body[..need].chunks_exact(record.max(1)).take(header.points) {
                asm.push(|f| types[f].read_le(&rec[offsets[f]..]));
            }
        }
        PcdData::BinaryCompressed => {
            let at = |o: usize| Location::Byte((header.data_start + o) as u64);
            if body.len() < 8 {
                return Err(IoError::malformed(
                    path,
                    at(body.len()),
                    "binary_compressed data lacks its 8-byte size prefix",
                ));
            }
            let compressed = u32::from_le_bytes([body[0], body[1], body[2], body[3]]) as usize;
            let raw = u32::from_le_bytes([body[4], body[5], body[6], body[7]]) as usize;
            if body.len() < 8 + compressed {
                return Err(IoError::malformed(
                    path,
                    at(body.len()),
                    format!(
                        "compressed data truncated: {compressed} bytes announced, {} present",
                        body.len() - 8
                    ),
                ));
            }
            if raw != total_bytes {
                return Err(IoError::malformed(
                    path,
                    at(4),
                    format!(
                        "uncompressed size {raw} does not match {} points of {record} bytes",
                        header.points
                    ),
                ));
            }
            let data = lzf::decompress(&body[8..8 + compressed], raw).map_err(|reason| {
                IoError::malformed(path, at(8), format!("corrupt LZF data: {reason}"))
            })?;
            // Field-major: scalar f of point i is at column_start[f] + i * size[f].
            let column_start: Vec<usize> = prefix_offsets(&types)
                .iter()
                .map(|o| o * header.points)
                .collect();
            for i in 0..header.points {
                asm.push(|f| types[f].read_le(&data[column_start[f] + i * types[f].size()..]));
            }
        }
    }
    Ok((asm.finish(), header.data, names))
}

fn prefix_offsets(types: &[Scalar]) -> Vec<usize> {
    types
        .iter()
        .scan(0, |acc, t| {
            let at = *acc;
            *acc += t.size();
            Some(at)
        })
        .collect()
}

fn read_ascii_body(
    path: &Path,
    body: &[u8],
    header: &Header,
    scalars: usize,
    asm: &mut Assembler,
) -> Result<(), IoError> {
    let text = std::str::from_utf8(body).map_err(|e| {
        IoError::malformed(
            path,
            Location::Byte((header.data_start + e.valid_up_to()) as u64),
            "ascii data is not UTF-8 text",
        )
    })?;
    let mut read = 0usize;
    let mut values = vec![0.0f64; scalars];
    for (k, line) in text.lines().enumerate() {
        let line_no = header.data_line + 1 + k;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if read == header.points {
            break;
        }
        let mut words = line.split_whitespace();
        for (slot, value) in values.iter_mut().enumerate() {
            let word = words.next().ok_or_else(|| {
                IoError::malformed(
                    path,
                    Location::Line(line_no),
                    format!("expected {scalars} values, found {slot}"),
                )
            })?;
            *value = parse_ascii_number(word).ok_or_else(|| {
                IoError::malformed(
                    path,
                    Location::Line(line_no),
                    format!("'{word}' is not a number"),
                )
            })?;
        }
        asm.push(|f| values[f]);
        read += 1;
    }
    if read < header.points {
        return Err(IoError::malformed(
            path,
            Location::File,
            format!(
                "ascii data truncated: header announces {} points, file has {read}",
                header.points
            ),
        ));
    }
    Ok(())
}

fn parse_ascii_number(word: &str) -> Option<f64> {
    // PCL writes "nan" for invalid points; Rust parses "nan", "NaN", "inf" already.
    word.parse::<f64>().ok()
}

/// Writes `cloud` as PCD with fields `x y z [view_x view_y view_z] [intensity] [time]`
/// (all F 4) in the given data mode.
pub fn write_pcd(cloud: &PointCloud, data: PcdData) -> Vec<u8> {
    let fields = cloud.field_names();
    let n = cloud.len();
    let mode = match data {
        PcdData::Ascii => "ascii",
        PcdData::Binary => "binary",
        PcdData::BinaryCompressed => "binary_compressed",
    };
    let ones = |s: &str| vec![s; fields.len()].join(" ");
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {}\nSIZE {}\nTYPE {}\nCOUNT {}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {mode}\n",
        fields.join(" "),
        ones("4"),
        ones("F"),
        ones("1"),
    )
    .into_bytes();
    match data {
        PcdData::Ascii => {
            for i in 0..n {
                push_ascii_row(&mut out, cloud, &fields, i);
            }
        }
        PcdData::Binary if fields.len() == 3 => {
            // Positions alone (a map's Autoware cloud): the records are the points.
            out.reserve(n * 12);
            for p in &cloud.points {
                for v in p {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        PcdData::Binary => {
            for i in 0..n {
                push_binary_row(&mut out, cloud, &fields, i);
            }
        }
        PcdData::BinaryCompressed => {
            let mut raw = Vec::with_capacity(n * fields.len() * 4);
            for f in &fields {
                for i in 0..n {
                    raw.extend_from_slice(&output_value(cloud, f, i).to_le_bytes());
                }
            }
            let packed = lzf::compress(&raw);
            out.extend_from_slice(&(packed.len() as u32).to_le_bytes());
            out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
            out.extend_from_slice(&packed);
        }
    }
    out
}
