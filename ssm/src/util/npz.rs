//! Parameter files readable outside Rust: NumPy's `.npz` archive (a zip of `.npy`
//! arrays), written and read without a zip or NumPy dependency.
//!
//! [`write_params`] stores each tensor of a [`ParamStore`] as `<name>.npy`
//! (float64, little-endian, C order), in the store's order, uncompressed;
//! `numpy.load(path)` reads it, keyed by the parameter names. [`read_params`]
//! reads such an archive back, and any archive `numpy.savez` writes (stored
//! entries, zip64 fields as NumPy writes them, `<f8` or `<f4` arrays);
//! `numpy.savez_compressed` archives (deflated entries) are refused with a
//! message saying so.

use std::fmt;
use std::io::Write;
use std::path::Path;

use autodiff::nn::ParamStore;
use autodiff::Tensor;

/// Why an `.npz` file could not be written or read; each names the file and,
/// where there is one, the entry.
#[derive(Debug)]
pub enum NpzError {
    /// Reading or writing the file failed.
    Io {
        /// The file.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not an archive this reader takes.
    Format {
        /// The file.
        path: String,
        /// The entry (`""` for the archive itself).
        entry: String,
        /// What is wrong.
        reason: String,
    },
}

impl fmt::Display for NpzError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            NpzError::Io { path, source } => write!(f, "{path}: {source}"),
            NpzError::Format { path, entry, reason } if entry.is_empty() => {
                write!(f, "{path}: not a readable .npz: {reason}")
            }
            NpzError::Format { path, entry, reason } => write!(f, "{path}: entry {entry:?}: {reason}"),
        }
    }
}

impl std::error::Error for NpzError {}

/// CRC-32 (IEEE, reflected), as zip stores it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

/// The `.npy` (format 1.0) bytes of a float64 array of `shape`.
pub fn npy_bytes(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let dims = match shape.len() {
        0 => String::new(),
        1 => format!("{},", shape[0]),
        _ => shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "),
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({dims}), }}");
    // Magic (6) + version (2) + length (2) + header + '\n', padded to 64 bytes.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 8 * data.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// An uncompressed zip archive of `(name, bytes)` entries (no zip64: every entry
/// and the archive must stay under 4 GiB).
fn zip_stored(entries: &[(String, Vec<u8>)]) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    for (name, bytes) in entries {
        let offset = u32::try_from(out.len()).map_err(|_| "archive over 4 GiB".to_string())?;
        let size = u32::try_from(bytes.len()).map_err(|_| format!("{name}: entry over 4 GiB"))?;
        let crc = crc32(bytes);
        let common = |v: &mut Vec<u8>| {
            v.extend_from_slice(&20u16.to_le_bytes()); // version needed
            v.extend_from_slice(&0u16.to_le_bytes()); // flags
            v.extend_from_slice(&0u16.to_le_bytes()); // method: stored
            v.extend_from_slice(&0u16.to_le_bytes()); // time
            v.extend_from_slice(&0x21u16.to_le_bytes()); // date: 1980-01-01
            v.extend_from_slice(&crc.to_le_bytes());
            v.extend_from_slice(&size.to_le_bytes());
            v.extend_from_slice(&size.to_le_bytes());
            v.extend_from_slice(&(name.len() as u16).to_le_bytes());
            v.extend_from_slice(&0u16.to_le_bytes()); // extra length
        };
        out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        common(&mut out);
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(bytes);
        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        central.extend_from_slice(&20u16.to_le_bytes()); // version made by
        common(&mut central);
        central.extend_from_slice(&[0u8; 6]); // comment length, disk, internal attributes
        central.extend_from_slice(&0u32.to_le_bytes()); // external attributes
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let cd_offset = u32::try_from(out.len()).map_err(|_| "archive over 4 GiB".to_string())?;
    let n = u16::try_from(entries.len()).map_err(|_| "over 65535 entries".to_string())?;
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&[0u8; 4]); // disk numbers
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&(central.len() as u32).to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes()); // comment length
    Ok(out)
}

/// The `.npz` bytes of named float64 arrays `(name, shape, values)`.
pub fn npz_bytes(arrays: &[(String, Vec<usize>, Vec<f64>)]) -> Result<Vec<u8>, String> {
    let entries: Vec<(String, Vec<u8>)> =
        arrays.iter().map(|(name, shape, data)| (format!("{name}.npy"), npy_bytes(shape, data))).collect();
    zip_stored(&entries)
}

/// Writes every tensor of `store` to `path` as a `.npz` archive keyed by name.
pub fn write_params(store: &ParamStore<f64>, path: &Path) -> Result<(), NpzError> {
    let arrays: Vec<(String, Vec<usize>, Vec<f64>)> =
        store.iter().map(|(name, t)| (name.to_string(), t.shape().to_vec(), t.data().to_vec())).collect();
    let bytes = npz_bytes(&arrays).map_err(|reason| NpzError::Format {
        path: path.display().to_string(),
        entry: String::new(),
        reason,
    })?;
    let io = |source| NpzError::Io { path: path.display().to_string(), source };
    let mut f = std::fs::File::create(path).map_err(io)?;
    f.write_all(&bytes).map_err(io)?;
    f.sync_all().map_err(io)
}

fn u16_at(b: &[u8], at: usize) -> Option<u16> {
    b.get(at..at + 2).map(|s| u16::from_le_bytes([s[0], s[1]]))
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    b.get(at..at + 4).map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

fn u64_at(b: &[u8], at: usize) -> Option<u64> {
    b.get(at..at + 8).map(|s| u64::from_le_bytes(s.try_into().expect("8 bytes")))
}

/// The named arrays of `.npz` bytes, in archive order: `(name, shape, values)`,
/// names without the `.npy` suffix. Errors are `(entry, reason)`.
pub fn parse_npz(bytes: &[u8]) -> Result<Vec<(String, Vec<usize>, Vec<f64>)>, (String, String)> {
    let archive = |r: &str| (String::new(), r.to_string());
    // The end-of-central-directory record: the last signature within 64 KiB + 22 bytes.
    let lo = bytes.len().saturating_sub(22 + 65_535);
    let eocd = (lo..bytes.len().saturating_sub(21))
        .rev()
        .find(|&i| u32_at(bytes, i) == Some(0x0605_4b50))
        .ok_or_else(|| archive("no zip end-of-central-directory record"))?;
    let short = || archive("truncated zip directory");
    let mut count = u16_at(bytes, eocd + 10).ok_or_else(short)? as u64;
    let mut cd = u32_at(bytes, eocd + 16).ok_or_else(short)? as u64;
    if count == 0xFFFF || cd == 0xFFFF_FFFF {
        // Zip64: the locator just before the record points at the zip64 record.
        let loc = eocd.checked_sub(20).ok_or_else(short)?;
        if u32_at(bytes, loc) != Some(0x0706_4b50) {
            return Err(archive("zip64 archive without a zip64 locator"));
        }
        let rec = u64_at(bytes, loc + 8).ok_or_else(short)? as usize;
        count = u64_at(bytes, rec + 32).ok_or_else(short)?;
        cd = u64_at(bytes, rec + 48).ok_or_else(short)?;
    }
    let mut at = cd as usize;
    let mut out = Vec::new();
    for _ in 0..count {
        if u32_at(bytes, at) != Some(0x0201_4b50) {
            return Err(archive("bad central directory entry"));
        }
        let method = u16_at(bytes, at + 10).ok_or_else(short)?;
        let mut size = u32_at(bytes, at + 20).ok_or_else(short)? as u64;
        let name_len = u16_at(bytes, at + 28).ok_or_else(short)? as usize;
        let extra_len = u16_at(bytes, at + 30).ok_or_else(short)? as usize;
        let comment_len = u16_at(bytes, at + 32).ok_or_else(short)? as usize;
        let mut local = u32_at(bytes, at + 42).ok_or_else(short)? as u64;
        let name_bytes = bytes.get(at + 46..at + 46 + name_len).ok_or_else(short)?;
        let name = String::from_utf8_lossy(name_bytes).to_string();
        let entry = |r: String| (name.clone(), r);
        // Zip64 extra field: the 64-bit values of the fields saturated above, in order.
        let extra = bytes.get(at + 46 + name_len..at + 46 + name_len + extra_len).ok_or_else(short)?;
        let mut e = 0;
        while e + 4 <= extra.len() {
            let (id, len) = (u16_at(extra, e).unwrap_or(0), u16_at(extra, e + 2).unwrap_or(0) as usize);
            if id == 1 {
                let mut p = e + 4;
                let uncompressed = u32_at(bytes, at + 24).ok_or_else(short)?;
                if uncompressed == 0xFFFF_FFFF {
                    p += 8;
                }
                if size == 0xFFFF_FFFF {
                    size = u64_at(extra, p).ok_or_else(short)?;
                    p += 8;
                }
                if local == 0xFFFF_FFFF {
                    local = u64_at(extra, p).ok_or_else(short)?;
                }
            }
            e += 4 + len;
        }
        at += 46 + name_len + extra_len + comment_len;
        if method != 0 {
            return Err(entry(format!(
                "compressed (zip method {method}); only uncompressed archives are read (numpy.savez, not savez_compressed)"
            )));
        }
        let local = local as usize;
        if u32_at(bytes, local) != Some(0x0403_4b50) {
            return Err(entry("bad local header".into()));
        }
        let start = local
            + 30
            + u16_at(bytes, local + 26).ok_or_else(short)? as usize
            + u16_at(bytes, local + 28).ok_or_else(short)? as usize;
        let data = bytes.get(start..start + size as usize).ok_or_else(|| entry("truncated data".into()))?;
        let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
        let (shape, values) = parse_npy(data).map_err(entry)?;
        out.push((key, shape, values));
    }
    Ok(out)
}

/// The shape and values (as f64) of `.npy` bytes holding a little-endian `<f8` or
/// `<f4` array in C order.
pub fn parse_npy(b: &[u8]) -> Result<(Vec<usize>, Vec<f64>), String> {
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" {
        return Err("not a .npy array (bad magic)".into());
    }
    let (hlen, hstart) = match b[6] {
        1 => (u16_at(b, 8).unwrap_or(0) as usize, 10),
        2 | 3 => (u32_at(b, 8).ok_or("truncated header")? as usize, 12),
        v => return Err(format!(".npy format version {v} is not read")),
    };
    let header = std::str::from_utf8(b.get(hstart..hstart + hlen).ok_or("truncated header")?)
        .map_err(|_| "header is not text".to_string())?;
    let field = |key: &str| -> Result<&str, String> {
        let i = header.find(&format!("'{key}'")).ok_or(format!("header has no '{key}'"))?;
        Ok(header[i + key.len() + 2..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr")?;
    let width = if descr.starts_with("'<f8'") {
        8
    } else if descr.starts_with("'<f4'") {
        4
    } else {
        return Err(format!(
            "dtype {} is not read (float64 '<f8' or float32 '<f4')",
            descr.split(',').next().unwrap_or("")
        ));
    };
    if field("fortran_order")?.starts_with("True") {
        return Err("Fortran-ordered arrays are not read (save a C-ordered array)".into());
    }
    let shape_text = field("shape")?;
    let close = shape_text.find(')').ok_or("malformed shape")?;
    let shape = shape_text[1..close]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("malformed shape {}", &shape_text[..=close])))
        .collect::<Result<Vec<usize>, String>>()?;
    let n: usize = shape.iter().product();
    let data = b.get(hstart + hlen..).unwrap_or(&[]);
    if data.len() != n * width {
        return Err(format!("shape {shape:?} needs {} bytes of data, found {}", n * width, data.len()));
    }
    let values = if width == 8 {
        data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))).collect()
    } else {
        data.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")) as f64).collect()
    };
    Ok((shape, values))
}

/// Reads a `.npz` archive into a parameter store (one tensor per array, in
/// archive order). With `like`, the result must have its names and shapes.
pub fn read_params(path: &Path, like: Option<&ParamStore<f64>>) -> Result<ParamStore<f64>, NpzError> {
    let p = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| NpzError::Io { path: p.clone(), source })?;
    let arrays = parse_npz(&bytes).map_err(|(entry, reason)| NpzError::Format { path: p.clone(), entry, reason })?;
    let mut store = ParamStore::new();
    for (name, shape, values) in arrays {
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(NpzError::Format { path: p, entry: name, reason: format!("value {i} is {}", values[i]) });
        }
        if store.id(&name).is_some() {
            return Err(NpzError::Format { path: p, entry: name, reason: "appears twice".into() });
        }
        store.add(&name, Tensor::new(&shape, values));
    }
    if let Some(like) = like {
        like.check_same_layout(&store).map_err(|e| NpzError::Format {
            path: p,
            entry: String::new(),
            reason: e.to_string(),
        })?;
    }
    Ok(store)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_of_a_known_string() {
        // The standard check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn npy_header_is_padded_to_64_bytes() {
        let b = npy_bytes(&[2, 3], &[0.0; 6]);
        assert_eq!(b.len(), 64 * ((10 + u16_at(&b, 8).unwrap() as usize) / 64) + 48);
        assert_eq!((10 + u16_at(&b, 8).unwrap() as usize) % 64, 0);
    }

    #[test]
    fn round_trip_keeps_names_shapes_and_bits() {
        let mut store = ParamStore::new();
        store.add("theta", Tensor::new(&[3], vec![0.5, -1.25, 1e-300]));
        store.add("net.w", Tensor::new(&[2, 2], vec![1.0, 2.0, 3.0, f64::MIN_POSITIVE]));
        store.add("scalar", Tensor::new(&[], vec![7.0]));
        let dir = std::env::temp_dir().join(format!("npz-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.npz");
        write_params(&store, &path).unwrap();
        let back = read_params(&path, Some(&store)).unwrap();
        assert_eq!(back, store);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn layout_mismatch_and_garbage_are_errors_naming_the_file() {
        let mut store = ParamStore::new();
        store.add("theta", Tensor::new(&[3], vec![0.5, -1.25, 1.0]));
        let mut other = ParamStore::new();
        other.add("theta", Tensor::new(&[2], vec![0.5, -1.25]));
        let dir = std::env::temp_dir().join(format!("npz-test-m-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.npz");
        write_params(&other, &path).unwrap();
        let e = read_params(&path, Some(&store)).unwrap_err().to_string();
        assert!(e.contains("p.npz") && e.contains("theta"), "{e}");
        std::fs::write(&path, b"not a zip").unwrap();
        let e = read_params(&path, None).unwrap_err().to_string();
        assert!(e.contains("p.npz") && e.contains("end-of-central-directory"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
