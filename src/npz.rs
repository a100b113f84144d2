//! NumPy `.npz` writing: a ZIP archive of `.npy` members, stored without compression, as
//! `numpy.savez` writes it (numpy/lib/_npyio_impl.py `_savez`: one `<key>.npy` member per array,
//! `zipfile.ZIP_STORED`), so `np.load(path)` gives a dict-like of the arrays. Members are `f64`
//! and `f32` arrays of any shape, 0-d `f64` and `i64` scalars, 0-d unicode strings (`<U…`,
//! what `np.array("neutral")` is) and 1-D arrays of them. Nothing here reads archives.
//!
//! The archive is plain ZIP (PKWARE's APPNOTE.TXT 6.3.x, sections 4.3.7 local file header,
//! 4.3.12 central directory header, 4.3.16 end of central directory), without ZIP64: a member
//! or the whole archive past 4 GiB is refused with an error, never truncated. Every timestamp is
//! the DOS epoch (1980-01-01 00:00), so the same arrays give the same bytes.

use crate::error::{invalid_arg, Result};
use crate::npy;

/// Local file header signature (APPNOTE 4.3.7).
const LOCAL_SIG: u32 = 0x0403_4b50;
/// Central directory file header signature (APPNOTE 4.3.12).
const CENTRAL_SIG: u32 = 0x0201_4b50;
/// End of central directory signature (APPNOTE 4.3.16).
const END_SIG: u32 = 0x0605_4b50;
/// "Version needed to extract": 2.0, the lowest that knows folders and stored data (4.4.3.2).
const VERSION: u16 = 20;
/// MS-DOS date of 1980-01-01: (year − 1980) << 9 | month << 5 | day (4.4.6).
const DOS_DATE: u16 = (1 << 5) | 1;
/// Sizes of the fixed parts of the three records.
const LOCAL_LEN: u64 = 30;
const CENTRAL_LEN: u64 = 46;
const END_LEN: u64 = 22;
/// ZIP32's largest size or offset. 0xFFFFFFFF itself means "see the ZIP64 record" (4.4.8),
/// so it is not a size this writer may write.
const ZIP32_MAX: u64 = u32::MAX as u64 - 1;
/// ZIP32's largest entry count (0xFFFF means "see ZIP64").
const MAX_MEMBERS: usize = u16::MAX as usize - 1;

/// An `.npz` archive being built in memory; [`Npz::finish`] gives its bytes.
#[derive(Debug, Default)]
pub struct Npz {
    /// Local headers and member data, in order.
    body: Vec<u8>,
    /// One central directory record per member.
    central: Vec<u8>,
    names: Vec<String>,
}

impl Npz {
    /// An empty archive.
    pub fn new() -> Npz {
        Npz::default()
    }

    /// Adds `name` (the key `np.load` gives) holding `data` in C order with `shape`, as `<f8`.
    pub fn add_f64(&mut self, name: &str, shape: &[usize], data: &[f64]) -> Result<()> {
        self.add_numbers(name, "<f8", shape, data.len(), 8, |out| {
            for v in data {
                out.extend_from_slice(&v.to_le_bytes());
            }
        })
    }

    /// Adds `name` holding `data` in C order with `shape`, as `<f4`.
    pub fn add_f32(&mut self, name: &str, shape: &[usize], data: &[f32]) -> Result<()> {
        self.add_numbers(name, "<f4", shape, data.len(), 4, |out| {
            for v in data {
                out.extend_from_slice(&v.to_le_bytes());
            }
        })
    }

    /// Adds `name` as a 0-d `<f8` array (`np.array(value)`).
    pub fn add_scalar_f64(&mut self, name: &str, value: f64) -> Result<()> {
        self.add_f64(name, &[], &[value])
    }

    /// Adds `name` as a 0-d `<i8` array (`np.array(value)` of a Python int on 64-bit NumPy).
    pub fn add_scalar_i64(&mut self, name: &str, value: i64) -> Result<()> {
        self.add_numbers(name, "<i8", &[], 1, 8, |out| {
            out.extend_from_slice(&value.to_le_bytes())
        })
    }

    /// Adds `name` as a 0-d unicode string: dtype `<U{n}` (n code points, at least 1), each
    /// stored as a little-endian UTF-32 unit, as `np.array(value)` holds a `str`. `str(a)` or
    /// `a.item()` of the loaded member gives `value` back.
    pub fn add_str(&mut self, name: &str, value: &str) -> Result<()> {
        if value.contains('\0') {
            // NumPy strips trailing NULs from `<U` values: a NUL would not come back.
            return Err(invalid_arg!(
                ".npz member `{name}`: a string with a NUL character"
            ));
        }
        let chars = value.chars().count().max(1);
        let descr = format!("<U{chars}");
        self.add_numbers(name, &descr, &[], 1, chars * 4, |out| {
            let start = out.len();
            for c in value.chars() {
                out.extend_from_slice(&(c as u32).to_le_bytes());
            }
            // The empty string is `<U1` holding one NUL, as NumPy stores it.
            out.resize(start + chars * 4, 0);
        })
    }

    /// Adds `name` as a 1-D unicode array of `values` (`np.array(["a", "bc"])`): dtype `<U{n}`,
    /// n the most code points of any value (at least 1), each value NUL-padded to n UTF-32 units,
    /// as NumPy stores it. `list(a)` of the loaded member gives `values` back.
    pub fn add_strs(&mut self, name: &str, values: &[&str]) -> Result<()> {
        if values.iter().any(|v| v.contains('\0')) {
            return Err(invalid_arg!(
                ".npz member `{name}`: a string with a NUL character"
            ));
        }
        let chars = values
            .iter()
            .map(|v| v.chars().count())
            .max()
            .unwrap_or(0)
            .max(1);
        let descr = format!("<U{chars}");
        self.add_numbers(
            name,
            &descr,
            &[values.len()],
            values.len(),
            chars * 4,
            |out| {
                for v in values {
                    let start = out.len();
                    for c in v.chars() {
                        out.extend_from_slice(&(c as u32).to_le_bytes());
                    }
                    out.resize(start + chars * 4, 0);
                }
            },
        )
    }

    /// Adds a member of `count` values of `width` bytes each, shaped `shape`, after checking the
    /// shape against `count` and the member and archive sizes against ZIP32's limits (before
    /// anything is allocated); `write` appends the values' bytes.
    fn add_numbers(
        &mut self,
        name: &str,
        descr: &str,
        shape: &[usize],
        count: usize,
        width: usize,
        write: impl FnOnce(&mut Vec<u8>),
    ) -> Result<()> {
        let member = format!("{name}.npy");
        self.check_name(name, &member)?;
        let elements = shape
            .iter()
            .try_fold(1u64, |a, &d| a.checked_mul(d as u64))
            .ok_or_else(|| invalid_arg!(".npz member `{name}`: shape {shape:?} overflows"))?;
        let header = npy::header(descr, shape);
        let size = elements
            .checked_mul(width as u64)
            .and_then(|b| b.checked_add(header.len() as u64))
            .filter(|&b| b <= ZIP32_MAX)
            .ok_or_else(|| {
                invalid_arg!(
                    ".npz member `{name}` of shape {shape:?} is larger than the 4 GiB a ZIP \
                     member may hold without ZIP64"
                )
            })?;
        if elements != count as u64 {
            return Err(invalid_arg!(
                ".npz member `{name}`: shape {shape:?} needs {elements} values, got {count}"
            ));
        }
        self.check_room(&member, size)?;
        let offset = self.body.len() as u64;
        let mut data = Vec::with_capacity(size as usize);
        data.extend_from_slice(&header);
        write(&mut data);
        debug_assert_eq!(data.len() as u64, size);
        let crc = crc32fast::hash(&data);
        let local = record_fields(crc, size as u32, &member);
        self.body.extend_from_slice(&LOCAL_SIG.to_le_bytes());
        self.body.extend_from_slice(&local);
        self.body.extend_from_slice(member.as_bytes());
        self.body.extend_from_slice(&data);
        self.central.extend_from_slice(&CENTRAL_SIG.to_le_bytes());
        self.central.extend_from_slice(&VERSION.to_le_bytes()); // version made by (MS-DOS, 2.0)
        self.central.extend_from_slice(&local);
        self.central.extend_from_slice(&[0; 2]); // comment length
        self.central.extend_from_slice(&[0; 2]); // disk number start
        self.central.extend_from_slice(&[0; 2]); // internal attributes
        self.central.extend_from_slice(&[0; 4]); // external attributes
        self.central
            .extend_from_slice(&(offset as u32).to_le_bytes());
        self.central.extend_from_slice(member.as_bytes());
        self.names.push(name.to_string());
        Ok(())
    }

    /// A key NumPy can give back: not empty, no path separators or NUL, not given twice.
    fn check_name(&self, name: &str, member: &str) -> Result<()> {
        if name.is_empty() || name.contains(['/', '\\', '\0']) {
            return Err(invalid_arg!(
                ".npz member name `{name}` must be non-empty, without `/`, `\\` or NUL"
            ));
        }
        if member.len() > u16::MAX as usize {
            return Err(invalid_arg!(
                ".npz member name is {} bytes long",
                name.len()
            ));
        }
        if self.names.iter().any(|n| n == name) {
            return Err(invalid_arg!(".npz member `{name}` is given twice"));
        }
        if self.names.len() >= MAX_MEMBERS {
            return Err(invalid_arg!(
                ".npz archives without ZIP64 hold at most {MAX_MEMBERS} members"
            ));
        }
        Ok(())
    }

    /// Refuses a member of `size` bytes whose records would put the archive past ZIP32's limits.
    fn check_room(&self, member: &str, size: u64) -> Result<()> {
        let name = member.len() as u64;
        fits_zip32(
            self.body.len() as u64,
            self.central.len() as u64,
            LOCAL_LEN + name + size,
            CENTRAL_LEN + name,
        )
        .map_err(|()| {
            invalid_arg!(
                ".npz archive would pass the 4 GiB a ZIP archive may hold without ZIP64 with \
                 member `{member}` ({size} bytes)"
            )
        })
    }

    /// The keys added so far, in order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// The archive's bytes: the members, the central directory and its end record.
    pub fn finish(self) -> Vec<u8> {
        // `check_room` kept every offset and size within u32 and the count within u16.
        let cd_offset = self.body.len() as u32;
        let cd_len = self.central.len() as u32;
        let count = self.names.len() as u16;
        let mut out = self.body;
        out.reserve(self.central.len() + END_LEN as usize);
        out.extend_from_slice(&self.central);
        out.extend_from_slice(&END_SIG.to_le_bytes());
        out.extend_from_slice(&[0; 4]); // this disk, disk with the central directory
        out.extend_from_slice(&count.to_le_bytes()); // entries on this disk
        out.extend_from_slice(&count.to_le_bytes()); // entries in all
        out.extend_from_slice(&cd_len.to_le_bytes());
        out.extend_from_slice(&cd_offset.to_le_bytes());
        out.extend_from_slice(&[0; 2]); // comment length
        out
    }
}

/// The fields a local header and a central record share after their signature (and, for the
/// central record, "version made by"): version needed, flags, method (0 = stored), DOS time and
/// date, CRC-32, compressed and uncompressed size (equal: stored), name length, extra length.
fn record_fields(crc: u32, size: u32, member: &str) -> Vec<u8> {
    let mut f = Vec::with_capacity(26);
    f.extend_from_slice(&VERSION.to_le_bytes());
    f.extend_from_slice(&0u16.to_le_bytes()); // flags: no data descriptor, names not UTF-8-flagged
    f.extend_from_slice(&0u16.to_le_bytes()); // method: stored
    f.extend_from_slice(&0u16.to_le_bytes()); // time 00:00:00
    f.extend_from_slice(&DOS_DATE.to_le_bytes());
    f.extend_from_slice(&crc.to_le_bytes());
    f.extend_from_slice(&size.to_le_bytes());
    f.extend_from_slice(&size.to_le_bytes());
    f.extend_from_slice(&(member.len() as u16).to_le_bytes());
    f.extend_from_slice(&0u16.to_le_bytes()); // extra field length
    f
}

/// Whether a member whose local part is `local` bytes and central record `central` bytes still
/// fits behind `body` bytes of members and `cd` bytes of central directory: its local header's
/// offset, the central directory's offset and size, all within ZIP32.
fn fits_zip32(body: u64, cd: u64, local: u64, central: u64) -> std::result::Result<(), ()> {
    let cd_offset = body.checked_add(local).ok_or(())?;
    let cd_len = cd.checked_add(central).ok_or(())?;
    let total = cd_offset
        .checked_add(cd_len)
        .and_then(|t| t.checked_add(END_LEN))
        .ok_or(())?;
    if body <= ZIP32_MAX
        && cd_offset <= ZIP32_MAX
        && cd_len <= ZIP32_MAX
        && total <= u32::MAX as u64
    {
        Ok(())
    } else {
        Err(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn u16_at(b: &[u8], i: usize) -> u16 {
        u16::from_le_bytes([b[i], b[i + 1]])
    }

    fn u32_at(b: &[u8], i: usize) -> u32 {
        u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
    }

    #[test]
    fn crc32_is_the_zip_polynomial() {
        // The CRC-32 check value of "123456789" (ISO-HDLC, the one ZIP uses).
        assert_eq!(crc32fast::hash(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn one_member_archive_has_the_zip_records_in_place() {
        let mut z = Npz::new();
        z.add_f64("a", &[2], &[1.5, -2.0]).unwrap();
        let b = z.finish();
        // Member data: the .npy header (10 + 57 bytes of text, padded to 128) then 16 bytes of
        // values.
        let npy_len = 128 + 16;
        let name = b"a.npy";
        // Local header.
        assert_eq!(u32_at(&b, 0), 0x0403_4b50);
        assert_eq!(u16_at(&b, 4), 20); // version needed
        assert_eq!(u16_at(&b, 8), 0); // stored
        assert_eq!(u16_at(&b, 12), 0x21); // 1980-01-01
        let data = &b[30 + name.len()..30 + name.len() + npy_len];
        assert_eq!(u32_at(&b, 14), crc32fast::hash(data));
        assert_eq!(u32_at(&b, 18), npy_len as u32);
        assert_eq!(u32_at(&b, 22), npy_len as u32);
        assert_eq!(u16_at(&b, 26), 5);
        assert_eq!(&b[30..35], name);
        assert_eq!(&data[..8], b"\x93NUMPY\x01\x00");
        assert_eq!(u16_at(data, 8), 118);
        let header = std::str::from_utf8(&data[10..128]).unwrap();
        assert!(header.starts_with("{'descr': '<f8', 'fortran_order': False, 'shape': (2,), }"));
        assert!(header.ends_with('\n'));
        assert_eq!(&data[128..136], &1.5f64.to_le_bytes());
        // Central record.
        let cd = 30 + name.len() + npy_len;
        assert_eq!(u32_at(&b, cd), 0x0201_4b50);
        assert_eq!(u32_at(&b, cd + 16), crc32fast::hash(data));
        assert_eq!(u32_at(&b, cd + 20), npy_len as u32);
        assert_eq!(u16_at(&b, cd + 28), 5);
        assert_eq!(u32_at(&b, cd + 42), 0); // local header offset
        assert_eq!(&b[cd + 46..cd + 51], name);
        // End record.
        let end = cd + 46 + name.len();
        assert_eq!(b.len(), end + 22);
        assert_eq!(u32_at(&b, end), 0x0605_4b50);
        assert_eq!(u16_at(&b, end + 8), 1);
        assert_eq!(u16_at(&b, end + 10), 1);
        assert_eq!(u32_at(&b, end + 12), 51); // central directory size
        assert_eq!(u32_at(&b, end + 16), cd as u32);
    }

    #[test]
    fn strings_and_scalars_are_0d_as_numpy_writes_them() {
        let mut z = Npz::new();
        z.add_str("gender", "neutral").unwrap();
        z.add_scalar_i64("num_betas", 16).unwrap();
        z.add_scalar_f64("fps", 30.0).unwrap();
        z.add_str("empty", "").unwrap();
        assert_eq!(z.names(), ["gender", "num_betas", "fps", "empty"]);
        let b = z.finish();
        // Where the values of the member whose header is `text` start: after the padded header,
        // whose length is stored just before it.
        let data_of = |text: &[u8]| {
            let at = b.windows(text.len()).position(|w| w == text).unwrap();
            at + u16_at(&b, at - 2) as usize
        };
        // 'n' 'e' ... as UTF-32LE.
        let data = data_of(b"{'descr': '<U7', 'fortran_order': False, 'shape': (), }");
        assert_eq!(&b[data..data + 8], b"n\0\0\0e\0\0\0");
        assert_eq!(&b[data + 24..data + 28], b"l\0\0\0");
        let i = data_of(b"{'descr': '<i8', 'fortran_order': False, 'shape': (), }");
        assert_eq!(&b[i..i + 8], &16i64.to_le_bytes());
        let e = data_of(b"{'descr': '<U1', 'fortran_order': False, 'shape': (), }");
        assert_eq!(&b[e..e + 4], &[0; 4]);
    }

    #[test]
    fn string_arrays_are_padded_to_the_longest() {
        let mut z = Npz::new();
        z.add_strs("joint_names", &["hip", "knee_joint", "é"])
            .unwrap();
        z.add_strs("none", &[]).unwrap();
        assert!(z.add_strs("bad", &["a", "b\0"]).is_err());
        let b = z.finish();
        let text = b"{'descr': '<U10', 'fortran_order': False, 'shape': (3,), }";
        let at = b.windows(text.len()).position(|w| w == text).unwrap();
        let data = at + u16_at(&b, at - 2) as usize;
        // "hip" then 7 NUL units, "knee_joint", then U+00E9 and 9 NUL units.
        assert_eq!(&b[data..data + 12], b"h\0\0\0i\0\0\0p\0\0\0");
        assert_eq!(&b[data + 12..data + 40], &[0; 28]);
        assert_eq!(&b[data + 40..data + 44], b"k\0\0\0");
        assert_eq!(&b[data + 80..data + 84], &0xE9u32.to_le_bytes());
        assert_eq!(&b[data + 84..data + 120], &[0; 36]);
        let empty = b"{'descr': '<U1', 'fortran_order': False, 'shape': (0,), }";
        assert!(b.windows(empty.len()).any(|w| w == empty));
    }

    #[test]
    fn f32_members_and_the_second_members_offset() {
        let mut z = Npz::new();
        z.add_f32("x", &[1, 2], &[0.5, 2.0]).unwrap();
        z.add_f32("y", &[0, 3], &[]).unwrap();
        let b = z.finish();
        let second = 30 + 5 + 128 + 8;
        assert_eq!(u32_at(&b, second), 0x0403_4b50);
        assert_eq!(&b[second + 30..second + 35], b"y.npy");
        let end = b.len() - 22;
        let cd = u32_at(&b, end + 16) as usize;
        assert_eq!(u32_at(&b, cd + 46 + 5 + 42), second as u32);
    }

    #[test]
    fn bad_members_are_errors_not_panics() {
        let mut z = Npz::new();
        let e = z.add_f64("a", &[3], &[1.0]).unwrap_err().to_string();
        assert!(e.contains("shape [3] needs 3 values, got 1"), "{e}");
        z.add_f64("a", &[1], &[1.0]).unwrap();
        let e = z.add_f64("a", &[1], &[1.0]).unwrap_err().to_string();
        assert!(e.contains("given twice"), "{e}");
        for bad in ["", "a/b", "c\\d"] {
            assert!(z.add_scalar_f64(bad, 1.0).is_err(), "{bad:?}");
        }
        assert!(z.add_str("s", "a\0b").is_err());
        // 2^32 f32 values = 16 GiB: refused from the shape alone, nothing allocated.
        let e = z
            .add_f32("big", &[1 << 20, 1 << 12], &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains("larger than the 4 GiB"), "{e}");
        let e = z
            .add_f64("huge", &[usize::MAX, 2], &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains("overflows"), "{e}");
        assert_eq!(z.names(), ["a"]);
    }

    #[test]
    fn the_archive_limit_counts_every_record() {
        let max = u32::MAX as u64;
        assert!(fits_zip32(0, 0, 100, 60).is_ok());
        assert!(fits_zip32(max - 200, 0, 100, 60).is_ok());
        // The end record would pass 4 GiB.
        assert!(fits_zip32(max - 170, 0, 100, 60).is_err());
        assert!(fits_zip32(max, 0, 1, 1).is_err());
        assert!(fits_zip32(u64::MAX, 0, 1, 1).is_err());
    }
}
