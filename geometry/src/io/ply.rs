//! PLY (Stanford polygon format): `ascii` and `binary_little_endian`, the `vertex`
//! element with `x y z` and optional fields; other elements are skipped.

use std::path::Path;

use super::error::{IoError, Location};
use super::fields::{Assembler, Scalar, push_ascii_row, push_binary_row};
use crate::cloud::PointCloud;

/// The encoding of a PLY file's body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyEncoding {
    /// Whitespace-separated text.
    Ascii,
    /// Packed little-endian values.
    BinaryLittleEndian,
}

enum Property {
    Scalar { name: String, ty: Scalar },
    List { count_ty: Scalar, item_ty: Scalar },
}

struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// Reads header lines one at a time, remembering the byte offset and line number.
struct HeaderLines<'a> {
    bytes: &'a [u8],
    offset: usize,
    line_no: usize,
}

impl HeaderLines<'_> {
    fn next_line(&mut self) -> Option<(usize, String)> {
        if self.offset >= self.bytes.len() {
            return None;
        }
        let rest = &self.bytes[self.offset..];
        let end = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
        let line = String::from_utf8_lossy(&rest[..end]).trim().to_string();
        self.offset += end + 1;
        self.line_no += 1;
        Some((self.line_no, line))
    }
}

fn parse_type(word: &str) -> Option<Scalar> {
    Some(match word {
        "char" | "int8" => Scalar::I8,
        "uchar" | "uint8" => Scalar::U8,
        "short" | "int16" => Scalar::I16,
        "ushort" | "uint16" => Scalar::U16,
        "int" | "int32" => Scalar::I32,
        "uint" | "uint32" => Scalar::U32,
        "float" | "float32" => Scalar::F32,
        "double" | "float64" => Scalar::F64,
        _ => return None,
    })
}

/// Reads a PLY file from its bytes; returns the cloud, the encoding and the vertex
/// property names.
pub fn read_ply(
    path: &Path,
    bytes: &[u8],
) -> Result<(PointCloud, PlyEncoding, Vec<String>), IoError> {
    let bad = |line: usize, reason: String| IoError::malformed(path, Location::Line(line), reason);
    let mut header = HeaderLines {
        bytes,
        offset: 0,
        line_no: 0,
    };
    match header.next_line() {
        Some((_, magic)) if magic == "ply" => {}
        _ => return Err(bad(1, "not a PLY file: first line is not 'ply'".into())),
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let (n, line) = header
            .next_line()
            .ok_or_else(|| bad(header.line_no, "header ends without 'end_header'".into()))?;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["end_header"] => break,
            ["format", "ascii", _] => encoding = Some(PlyEncoding::Ascii),
            ["format", "binary_little_endian", _] => {
                encoding = Some(PlyEncoding::BinaryLittleEndian)
            }
            ["format", other, ..] => {
                return Err(bad(
                    n,
                    format!(
                        "unsupported PLY format '{other}'; expected ascii or binary_little_endian"
                    ),
                ));
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| bad(n, format!("element count '{count}' is not an integer")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", count_ty, item_ty, _name] => {
                let (Some(count_ty), Some(item_ty)) = (parse_type(count_ty), parse_type(item_ty))
                else {
                    return Err(bad(n, format!("unknown list types in '{line}'")));
                };
                let element = elements
                    .last_mut()
                    .ok_or_else(|| bad(n, "property before any element".into()))?;
                element
                    .properties
                    .push(Property::List { count_ty, item_ty });
            }
            ["property", ty, name] => {
                let ty = parse_type(ty)
                    .ok_or_else(|| bad(n, format!("unknown property type '{ty}'")))?;
                let element = elements
                    .last_mut()
                    .ok_or_else(|| bad(n, "property before any element".into()))?;
                element.properties.push(Property::Scalar {
                    name: name.to_string(),
                    ty,
                });
            }
            _ => return Err(bad(n, format!("unexpected header line '{line}'"))),
        }
    }
    let header_lines = header.line_no;
    let encoding =
        encoding.ok_or_else(|| bad(header_lines, "header has no 'format' line".into()))?;
    let body_start = header.offset.min(bytes.len());
    let vertex = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| bad(header_lines, "no 'vertex' element".into()))?;
    let names: Vec<String> = elements[vertex]
        .properties
        .iter()
        .map(|p| match p {
            Property::Scalar { name, .. } => name.clone(),
            Property::List { .. } => String::new(),
        })
        .collect();
    let body = &bytes[body_start..];
    let mut asm = Assembler::new(&names, elements[vertex].count.min(body.len()))
        .map_err(|reason| bad(header_lines, reason))?;
    match encoding {
        PlyEncoding::Ascii => read_ascii(path, body, header_lines, &elements, vertex, &mut asm)?,
        PlyEncoding::BinaryLittleEndian => {
            read_binary(path, body, body_start, &elements, vertex, &mut asm)?
        }
    }
    Ok((asm.finish(), encoding, names))
}

fn read_ascii(
    path: &Path,
    body: &[u8],
    header_lines: usize,
    elements: &[Element],
    vertex: usize,
    asm: &mut Assembler,
) -> Result<(), IoError> {
    let text = String::from_utf8_lossy(body);
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, l)| (header_lines + 1 + k, l));
    let mut values = Vec::new();
    for (e, element) in elements.iter().enumerate() {
        for _ in 0..element.count {
            let (line_no, line) = lines.next().ok_or_else(|| {
                IoError::malformed(
                    path,
                    Location::File,
                    format!(
                        "file ends inside element '{}' ({} announced)",
                        element.name, element.count
                    ),
                )
            })?;
            if e != vertex {
                continue;
            }
            values.clear();
            for word in line.split_whitespace().take(element.properties.len()) {
                values.push(word.parse::<f64>().map_err(|_| {
                    IoError::malformed(
                        path,
                        Location::Line(line_no),
                        format!("'{word}' is not a number"),
                    )
                })?);
            }
            if values.len() < element.properties.len() {
                return Err(IoError::malformed(
                    path,
                    Location::Line(line_no),
                    format!(
                        "expected {} values, found {}",
                        element.properties.len(),
                        values.len()
                    ),
                ));
            }
            asm.push(|f| values[f]);
        }
    }
    Ok(())
}

fn read_binary(
    path: &Path,
    body: &[u8],
    body_start: usize,
    elements: &[Element],
    vertex: usize,
    asm: &mut Assembler,
) -> Result<(), IoError> {
    let mut at = 0usize;
    let truncated = |at: usize, what: &str| {
        IoError::malformed(
            path,
            Location::Byte((body_start + at) as u64),
            format!("binary data truncated inside {what}"),
        )
    };
    let mut values = vec![0.0f64; elements[vertex].properties.len()];
    for (e, element) in elements.iter().enumerate() {
        if element.properties.is_empty() {
            continue; // Holds no bytes, however large its count.
        }
        for _ in 0..element.count {
            for (p, property) in element.properties.iter().enumerate() {
                match property {
                    Property::Scalar { ty, .. } => {
                        let bytes = body
                            .get(at..at + ty.size())
                            .ok_or_else(|| truncated(at, &element.name))?;
                        if e == vertex {
                            values[p] = ty.read_le(bytes);
                        }
                        at += ty.size();
                    }
                    Property::List { count_ty, item_ty } => {
                        let bytes = body
                            .get(at..at + count_ty.size())
                            .ok_or_else(|| truncated(at, &element.name))?;
                        let count = count_ty.read_le(bytes).max(0.0) as usize;
                        let skip = count
                            .checked_mul(item_ty.size())
                            .and_then(|s| s.checked_add(count_ty.size()));
                        match skip.and_then(|s| at.checked_add(s)) {
                            Some(end) if end <= body.len() => at = end,
                            _ => return Err(truncated(body.len(), &element.name)),
                        }
                    }
                }
            }
            if e == vertex {
                asm.push(|f| values[f]);
            }
        }
    }
    Ok(())
}

/// Writes `cloud` as PLY with float vertex properties named as
/// [`PointCloud::field_names`].
pub fn write_ply(cloud: &PointCloud, encoding: PlyEncoding) -> Vec<u8> {
    let fields = cloud.field_names();
    let format = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
    };
    let mut out = format!(
        "ply\nformat {format} 1.0\ncomment written by kfmap\nelement vertex {}\n",
        cloud.len()
    );
    for f in &fields {
        out.push_str(&format!("property float {f}\n"));
    }
    out.push_str("end_header\n");
    let mut out = out.into_bytes();
    for i in 0..cloud.len() {
        match encoding {
            PlyEncoding::Ascii => push_ascii_row(&mut out, cloud, &fields, i),
            PlyEncoding::BinaryLittleEndian => push_binary_row(&mut out, cloud, &fields, i),
        }
    }
    out
}
