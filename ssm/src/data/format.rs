//! Reading and writing dataset directories (SPEC §4).
//!
//! The CSV files hold only integers and numbers, so a small strict reader is
//! used instead of a general CSV parser: comma-separated fields, surrounding
//! spaces trimmed, blank lines skipped, no quoting. Line 1 must be the exact
//! header. Numbers are written in Rust's shortest round-trip form, so
//! write -> read is bit-exact.

use super::builder::{assemble, Rec, Records};
use super::error::{DataError, Place, Problem};
use super::meta::{parse_meta, render_meta};
use super::{
    Action, BoxDetection, DataLayout, Dataset, Object, ObservationKind, Observations, Pose, Prior, State, ACTIONS_FILE,
    ACTION_COLUMNS, AV_COLUMNS, AV_FILE, BOXES_FILE, BOX_COLUMNS, META_FILE, OBJECTS_FILE, OBJECT_COLUMNS, POINTS_FILE,
    POINT_COLUMNS, STATES_FILE, STATE_COLUMNS,
};
use std::collections::HashSet;
use std::fs;
use std::io::{self, BufRead, BufWriter, Write};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// The most columns any dataset file has.
const MAX_COLUMNS: usize = 14;

/// The longest line a CSV file may have, in bytes. A row of fourteen numbers
/// in shortest round-trip form takes under 400; the bound lets a reader stop
/// at a line that cannot be a row (a file without line breaks, say) before
/// holding it in memory.
pub(crate) const MAX_LINE_BYTES: usize = 1 << 20;

/// The largest `meta.json` read, in bytes (the file holds four short fields).
pub(crate) const MAX_META_BYTES: u64 = 1 << 20;

/// Reads the text of `meta.json`; a missing file is [`DataError::MissingFile`],
/// one over [`MAX_META_BYTES`] an error before it is read.
fn read_meta_text(path: &Path) -> Result<String, DataError> {
    let file = fs::File::open(path).map_err(|e| {
        if e.kind() == io::ErrorKind::NotFound {
            DataError::MissingFile { path: path.to_path_buf() }
        } else {
            DataError::io(path, e)
        }
    })?;
    let mut bytes = Vec::new();
    io::Read::read_to_end(&mut io::Read::take(file, MAX_META_BYTES + 1), &mut bytes)
        .map_err(|e| DataError::io(path, e))?;
    if bytes.len() as u64 > MAX_META_BYTES {
        return Err(DataError::Meta {
            line: 1,
            field: "-".into(),
            message: format!("the file is over {MAX_META_BYTES} bytes; meta.json holds four short fields"),
        });
    }
    String::from_utf8(bytes)
        .map_err(|e| DataError::io(path, io::Error::new(io::ErrorKind::InvalidData, e.utf8_error())))
}

/// One data row of a CSV file, with typed accessors that report bad fields.
pub(crate) struct Row<'a> {
    file: &'a str,
    line: usize,
    columns: &'a [&'a str],
    fields: [&'a str; MAX_COLUMNS],
}

impl Row<'_> {
    fn place(&self) -> Place {
        Place::Line(self.line)
    }

    fn malformed(&self, i: usize, expected: &'static str) -> DataError {
        DataError::invalid(
            self.file,
            self.place(),
            self.columns[i],
            Problem::Malformed { text: self.fields[i].to_string(), expected },
        )
    }

    /// Field `i` as an integer.
    fn int(&self, i: usize) -> Result<i64, DataError> {
        self.fields[i].parse::<i64>().map_err(|_| self.malformed(i, "an integer"))
    }

    /// Field `i` as a finite number.
    fn num(&self, i: usize) -> Result<f64, DataError> {
        let text = self.fields[i];
        let v: f64 = text.parse().map_err(|_| self.malformed(i, "a number"))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(DataError::invalid(
                self.file,
                self.place(),
                self.columns[i],
                Problem::NonFinite { text: text.to_string() },
            ))
        }
    }
}

/// Opens a file for reading; a missing file is [`DataError::MissingFile`].
fn open(path: &Path) -> Result<io::BufReader<fs::File>, DataError> {
    fs::File::open(path).map(io::BufReader::new).map_err(|e| {
        if e.kind() == io::ErrorKind::NotFound {
            DataError::MissingFile { path: path.to_path_buf() }
        } else {
            DataError::io(path, e)
        }
    })
}

/// Checks line 1 of the CSV file `name` against its `columns`.
fn check_header(name: &'static str, columns: &'static [&'static str], line: &str) -> Result<(), DataError> {
    let line = line.strip_prefix('\u{feff}').unwrap_or(line);
    let header: Vec<&str> = line.split(',').map(str::trim).collect();
    if header == columns {
        return Ok(());
    }
    let i = header.iter().zip(columns).position(|(a, b)| a != b).unwrap_or(header.len().min(columns.len()));
    let column = columns.get(i).or(header.get(i)).copied().unwrap_or("-");
    Err(DataError::invalid(
        name,
        Place::Line(1),
        column,
        Problem::Header { expected: columns.join(","), found: header.join(",") },
    ))
}

/// Streams the CSV file `name` of `dir` line by line (the file is never held in
/// memory whole): checks the header and the field count of every row, and hands
/// each row to `visit`.
fn read_rows(
    dir: &Path,
    name: &'static str,
    columns: &'static [&'static str],
    mut visit: impl FnMut(&Row<'_>) -> Result<(), DataError>,
) -> Result<(), DataError> {
    let path = dir.join(name);
    let mut reader = open(&path)?;
    let mut buffer = String::new();
    let mut line_no = 0;
    loop {
        buffer.clear();
        let limit = MAX_LINE_BYTES as u64 + 1;
        if io::Read::take(&mut reader, limit).read_line(&mut buffer).map_err(|e| DataError::io(&path, e))? == 0 {
            break;
        }
        line_no += 1;
        if buffer.len() > MAX_LINE_BYTES {
            return Err(DataError::invalid(
                name,
                Place::Line(line_no),
                "-",
                Problem::Other(format!("line longer than {MAX_LINE_BYTES} bytes")),
            ));
        }
        let line = buffer.strip_suffix('\n').unwrap_or(&buffer);
        let line = line.strip_suffix('\r').unwrap_or(line);
        if line_no == 1 {
            check_header(name, columns, line)?;
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        let mut row = Row { file: name, line: line_no, columns, fields: [""; MAX_COLUMNS] };
        let mut count = 0;
        for f in line.split(',') {
            if count < MAX_COLUMNS {
                row.fields[count] = f.trim();
            }
            count += 1;
        }
        if count != columns.len() {
            let column = if count < columns.len() {
                columns[count].to_string()
            } else {
                format!("(extra field {})", columns.len() + 1)
            };
            return Err(DataError::invalid(
                name,
                Place::Line(line_no),
                column,
                Problem::FieldCount { expected: columns.len(), found: count },
            ));
        }
        visit(&row)?;
    }
    if line_no == 0 {
        check_header(name, columns, "")?;
    }
    Ok(())
}

/// Reads the CSV file `name` of `dir` ([`read_rows`]), turning each row into a
/// `T` with `parse`.
fn read_csv<T>(
    dir: &Path,
    name: &'static str,
    columns: &'static [&'static str],
    mut parse: impl FnMut(&Row<'_>) -> Result<T, DataError>,
) -> Result<Vec<T>, DataError> {
    let mut out = Vec::new();
    read_rows(dir, name, columns, |row| {
        out.push(parse(row)?);
        Ok(())
    })?;
    Ok(out)
}

/// Reads the (scene, object, t)-keyed CSV file `name` of `dir`, skipping the rows
/// of objects `shard` leaves to other processes before parsing their values.
fn read_keyed<T>(
    dir: &Path,
    name: &'static str,
    columns: &'static [&'static str],
    shard: Option<&Shard>,
    mut value: impl FnMut(&Row<'_>) -> Result<T, DataError>,
) -> Result<Vec<Rec<T>>, DataError> {
    let mut out = Vec::new();
    read_rows(dir, name, columns, |r| {
        let (scene, object) = (r.int(0)?, r.int(1)?);
        if shard.is_some_and(|s| s.elsewhere(scene, object)) {
            return Ok(());
        }
        let t = r.int(2)?;
        out.push(Rec { place: r.place(), scene, object, t, value: value(r)? });
        Ok(())
    })?;
    Ok(out)
}

/// The objects one process of a job reads ([`read_shard`]).
struct Shard<'a> {
    /// Every object of `objects.csv`.
    known: HashSet<(i64, i64)>,
    /// This process's objects.
    keep: &'a HashSet<(i64, i64)>,
}

impl Shard<'_> {
    /// Whether the rows of (`scene`, `object`) belong to another process. Rows
    /// of an object `objects.csv` lacks are kept, so that reading reports them.
    fn elsewhere(&self, scene: i64, object: i64) -> bool {
        !self.keep.contains(&(scene, object)) && self.known.contains(&(scene, object))
    }
}

/// Reads and validates the dataset in `dir`.
pub(crate) fn read_dir(dir: &Path) -> Result<Dataset, DataError> {
    read_objects(dir, None)
}

/// Reads and validates the part of the dataset in `dir` that one process of a
/// data-parallel job owns: every scene, and of the objects only those in
/// `keep` (keys `(scene, object)`). The rows of other objects are skipped
/// before their values are parsed; they are validated by the process that owns
/// them. Rows of objects `objects.csv` does not list are an error, as in
/// [`read_dir`].
pub(crate) fn read_shard(dir: &Path, keep: &HashSet<(i64, i64)>) -> Result<Dataset, DataError> {
    read_objects(dir, Some(keep))
}

/// The observation kind of the dataset in `dir`, from which file it has.
fn observation_kind(dir: &Path) -> Result<ObservationKind, DataError> {
    match (dir.join(POINTS_FILE).exists(), dir.join(BOXES_FILE).exists()) {
        (true, false) => Ok(ObservationKind::Points),
        (false, true) => Ok(ObservationKind::Boxes),
        (both, _) => Err(DataError::ObservationFiles { dir: dir.to_path_buf(), both }),
    }
}

/// [`read_dir`] (`keep` = `None`) or [`read_shard`].
fn read_objects(dir: &Path, keep: Option<&HashSet<(i64, i64)>>) -> Result<Dataset, DataError> {
    let meta = parse_meta(&read_meta_text(&dir.join(META_FILE))?)?;
    let kind = observation_kind(dir)?;
    let av = read_csv(dir, AV_FILE, &AV_COLUMNS, |r| {
        // Parse in column order so the first bad column is reported.
        let (scene, t) = (r.int(0)?, r.int(1)?);
        let value = Pose { x: r.num(2)?, y: r.num(3)?, yaw: r.num(4)? };
        Ok(Rec { place: r.place(), scene, object: 0, t, value })
    })?;
    let mut objects = read_csv(dir, OBJECTS_FILE, &OBJECT_COLUMNS, |r| {
        let (scene, id) = (r.int(0)?, r.int(1)?);
        let (length, width) = (r.num(2)?, r.num(3)?);
        let mut v = [0.0; 10];
        for (i, x) in v.iter_mut().enumerate() {
            *x = r.num(4 + i)?;
        }
        let mean = State::from_array([v[0], v[1], v[2], v[3], v[4]]);
        let sd = State::from_array([v[5], v[6], v[7], v[8], v[9]]);
        Ok(Rec {
            place: r.place(),
            scene,
            object: id,
            t: 0,
            value: Object { scene, id, length, width, prior: Prior { mean, sd } },
        })
    })?;
    let shard = keep.map(|keep| Shard { known: objects.iter().map(|r| (r.scene, r.object)).collect(), keep });
    if let Some(shard) = &shard {
        objects.retain(|r| !shard.elsewhere(r.scene, r.object));
    }
    let shard = shard.as_ref();
    let mut records = Records { av, objects, ..Records::default() };
    match kind {
        ObservationKind::Points => {
            records.points = read_keyed(dir, POINTS_FILE, &POINT_COLUMNS, shard, |r| Ok([r.num(3)?, r.num(4)?]))?
        }
        ObservationKind::Boxes => {
            records.boxes = read_keyed(dir, BOXES_FILE, &BOX_COLUMNS, shard, |r| {
                Ok(BoxDetection {
                    x: r.num(3)?,
                    y: r.num(4)?,
                    yaw: r.num(5)?,
                    length: r.num(6)?,
                    width: r.num(7)?,
                    score: r.num(8)?,
                })
            })?
        }
    }
    if dir.join(STATES_FILE).exists() {
        records.states = Some(read_keyed(dir, STATES_FILE, &STATE_COLUMNS, shard, |r| {
            let mut v = [0.0; 5];
            for (i, x) in v.iter_mut().enumerate() {
                *x = r.num(3 + i)?;
            }
            Ok(State::from_array(v))
        })?);
    }
    if dir.join(ACTIONS_FILE).exists() {
        records.actions = Some(read_keyed(dir, ACTIONS_FILE, &ACTION_COLUMNS, shard, |r| {
            Ok(Action { accel: r.num(3)?, pinch: r.num(4)? })
        })?);
    }
    assemble(meta, kind, records)
}

/// The first pass of a sharded read: the dataset's layout from `meta.json`,
/// the keys of `av.csv` and `objects.csv` and a count of the observation rows
/// of each object, without parsing any value. An object whose scene `av.csv`
/// lacks is reported here, as [`read_dir`] would.
pub(crate) fn read_layout(dir: &Path) -> Result<DataLayout, DataError> {
    let meta = parse_meta(&read_meta_text(&dir.join(META_FILE))?)?;
    let kind = observation_kind(dir)?;
    let mut scene_ids = Vec::new();
    read_rows(dir, AV_FILE, &AV_COLUMNS, |r| {
        scene_ids.push(r.int(0)?);
        Ok(())
    })?;
    scene_ids.sort_unstable();
    scene_ids.dedup();
    let mut objects = Vec::new();
    read_rows(dir, OBJECTS_FILE, &OBJECT_COLUMNS, |r| {
        let (scene, id) = (r.int(0)?, r.int(1)?);
        if scene_ids.binary_search(&scene).is_err() {
            return Err(DataError::invalid(OBJECTS_FILE, r.place(), "scene", Problem::UnknownScene { scene }));
        }
        objects.push((scene, id));
        Ok(())
    })?;
    objects.sort_unstable();
    let mut units = vec![0usize; objects.len()];
    let (file, columns): (&'static str, &'static [&'static str]) = match kind {
        ObservationKind::Points => (POINTS_FILE, &POINT_COLUMNS),
        ObservationKind::Boxes => (BOXES_FILE, &BOX_COLUMNS),
    };
    let mut last: Option<((i64, i64), usize)> = None;
    read_rows(dir, file, columns, |r| {
        let key = (r.int(0)?, r.int(1)?);
        let o = match last {
            Some((k, o)) if k == key => Some(o),
            _ => objects.binary_search(&key).ok(),
        };
        if let Some(o) = o {
            units[o] += 1;
            last = Some((key, o));
        }
        Ok(())
    })?;
    Ok(DataLayout::new(meta, &scene_ids, objects, units))
}

/// Distinguishes temporary files of concurrent writers in one process.
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `dir/name` atomically: into a temporary file in `dir`, synced, then
/// renamed over the target. On failure the temporary file is removed and the
/// previous `dir/name` (if any) is untouched.
fn write_atomic(
    dir: &Path,
    name: &str,
    body: impl FnOnce(&mut BufWriter<fs::File>) -> io::Result<()>,
) -> Result<(), DataError> {
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let result = (|| -> io::Result<()> {
        let mut w = BufWriter::new(fs::File::create(&tmp)?);
        body(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(DataError::io(tmp, e));
    }
    let target = dir.join(name);
    fs::rename(&tmp, &target).map_err(|e| {
        let _ = fs::remove_file(&tmp);
        DataError::io(target, e)
    })
}

/// Writes a row of numbers after the integer key fields.
fn row(w: &mut impl Write, key: &[i64], values: &[f64]) -> io::Result<()> {
    for (i, k) in key.iter().enumerate() {
        if i > 0 {
            w.write_all(b",")?;
        }
        write!(w, "{k}")?;
    }
    for v in values {
        // `{:?}` is the shortest representation that parses back to the same bits.
        write!(w, ",{v:?}")?;
    }
    w.write_all(b"\n")
}

fn header(w: &mut impl Write, columns: &[&str]) -> io::Result<()> {
    writeln!(w, "{}", columns.join(","))
}

/// Writes `ds` into `dir`.
pub(crate) fn write_dir(ds: &Dataset, dir: &Path) -> Result<(), DataError> {
    fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    let objects = ds.objects();
    let key = |o: usize, t: usize| [objects[o].scene, objects[o].id, t as i64];

    write_atomic(dir, AV_FILE, |w| {
        header(w, &AV_COLUMNS)?;
        for s in ds.scenes() {
            for (t, p) in s.av.iter().enumerate() {
                row(w, &[s.id, t as i64], &[p.x, p.y, p.yaw])?;
            }
        }
        Ok(())
    })?;
    write_atomic(dir, OBJECTS_FILE, |w| {
        header(w, &OBJECT_COLUMNS)?;
        for o in objects {
            let m = o.prior.mean.to_array();
            let s = o.prior.sd.to_array();
            let mut v = vec![o.length, o.width];
            v.extend_from_slice(&m);
            v.extend_from_slice(&s);
            row(w, &[o.scene, o.id], &v)?;
        }
        Ok(())
    })?;
    let stale_obs = match ds.observations() {
        Observations::Points(p) => {
            write_atomic(dir, POINTS_FILE, |w| {
                header(w, &POINT_COLUMNS)?;
                for (o, t, xy) in p.iter() {
                    row(w, &key(o, t), &xy)?;
                }
                Ok(())
            })?;
            BOXES_FILE
        }
        Observations::Boxes(b) => {
            write_atomic(dir, BOXES_FILE, |w| {
                header(w, &BOX_COLUMNS)?;
                for (o, t, d) in b.iter() {
                    row(w, &key(o, t), &[d.x, d.y, d.yaw, d.length, d.width, d.score])?;
                }
                Ok(())
            })?;
            POINTS_FILE
        }
    };
    let mut stale = vec![stale_obs];
    match ds.states() {
        Some(states) => write_atomic(dir, STATES_FILE, |w| {
            header(w, &STATE_COLUMNS)?;
            for (o, t, s) in states.iter() {
                row(w, &key(o, t), &s.to_array())?;
            }
            Ok(())
        })?,
        None => stale.push(STATES_FILE),
    }
    match ds.actions() {
        Some(actions) => write_atomic(dir, ACTIONS_FILE, |w| {
            header(w, &ACTION_COLUMNS)?;
            for (o, t, a) in actions.iter() {
                row(w, &key(o, t), &[a.accel, a.pinch])?;
            }
            Ok(())
        })?,
        None => stale.push(ACTIONS_FILE),
    }
    let meta_text = render_meta(&ds.meta());
    write_atomic(dir, META_FILE, |w| w.write_all(meta_text.as_bytes()))?;
    for name in stale {
        let path = dir.join(name);
        match fs::remove_file(&path) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(DataError::io(path, e)),
        }
    }
    Ok(())
}
