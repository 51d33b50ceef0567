//! Reading ROS messages: ROS 2's plain CDR (XCDR1) and ROS 1's serialisation. CDR has a 4-byte
//! encapsulation header (its second byte says the byte order), then fields in order, each
//! aligned to its own size measured from the end of the header; strings are a `u32` length
//! counting a final NUL, sequences a `u32` count. ROS 1 is the same little-endian fields with
//! no header, no alignment and no NUL (and a `seq` in every `Header`). Only what the message
//! readers need.

/// How a message is serialised.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// ROS 2: CDR.
    Cdr,
    /// ROS 1.
    Ros1,
}

/// A cursor over one CDR message; every read checks bounds and says what was truncated.
pub struct Cdr<'a> {
    data: &'a [u8],
    pos: usize,
    little: bool,
    /// ROS 1: no alignment, and headers carry a `seq`.
    pub ros1: bool,
}

/// Result of a CDR read: the error says which field could not be read.
pub type CdrResult<T> = std::result::Result<T, String>;

impl<'a> Cdr<'a> {
    /// A reader of a message in `encoding`.
    pub fn with(data: &'a [u8], encoding: Encoding) -> CdrResult<Self> {
        match encoding {
            Encoding::Cdr => Self::new(data),
            Encoding::Ros1 => Ok(Cdr { data, pos: 0, little: true, ros1: true }),
        }
    }

    /// A reader positioned after the encapsulation header.
    pub fn new(data: &'a [u8]) -> CdrResult<Self> {
        if data.len() < 4 {
            return Err("message shorter than its CDR header".into());
        }
        let little = match data[1] {
            0 | 2 => false,
            1 | 3 => true,
            other => return Err(format!("unknown CDR encapsulation {other}")),
        };
        Ok(Cdr { data: &data[4..], pos: 0, little, ros1: false })
    }

    fn take(&mut self, n: usize, align: usize, what: &str) -> CdrResult<&'a [u8]> {
        let start = if self.ros1 { self.pos } else { self.pos.next_multiple_of(align) };
        let end = start.checked_add(n).filter(|e| *e <= self.data.len());
        let end = end.ok_or_else(|| format!("message ends inside {what}"))?;
        self.pos = end;
        Ok(&self.data[start..end])
    }

    fn bytes<const N: usize>(&mut self, what: &str) -> CdrResult<[u8; N]> {
        let b: [u8; N] = self.take(N, N, what)?.try_into().expect("N bytes");
        Ok(b)
    }

    /// A `u8` (also `bool` and `char`).
    pub fn u8(&mut self, what: &str) -> CdrResult<u8> {
        Ok(self.bytes::<1>(what)?[0])
    }

    /// A `u32`.
    pub fn u32(&mut self, what: &str) -> CdrResult<u32> {
        let b = self.bytes::<4>(what)?;
        Ok(if self.little { u32::from_le_bytes(b) } else { u32::from_be_bytes(b) })
    }

    /// An `i32`.
    pub fn i32(&mut self, what: &str) -> CdrResult<i32> {
        Ok(self.u32(what)? as i32)
    }

    /// An `f32`.
    pub fn f32(&mut self, what: &str) -> CdrResult<f32> {
        Ok(f32::from_bits(self.u32(what)?))
    }

    /// An `f64`.
    pub fn f64(&mut self, what: &str) -> CdrResult<f64> {
        let b = self.bytes::<8>(what)?;
        Ok(f64::from_bits(if self.little { u64::from_le_bytes(b) } else { u64::from_be_bytes(b) }))
    }

    /// `N` consecutive `f64`s (a fixed-size array).
    pub fn f64s<const N: usize>(&mut self, what: &str) -> CdrResult<[f64; N]> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }

    /// A string.
    pub fn string(&mut self, what: &str) -> CdrResult<String> {
        let n = self.u32(what)? as usize;
        let raw = self.take(n, 1, what)?;
        let text = raw.strip_suffix(&[0]).unwrap_or(raw);
        String::from_utf8(text.to_vec()).map_err(|_| format!("{what} is not UTF-8"))
    }

    /// A sequence of bytes (borrowed).
    pub fn byte_seq(&mut self, what: &str) -> CdrResult<&'a [u8]> {
        let n = self.u32(what)? as usize;
        self.take(n, 1, what)
    }

    /// A count of `elem`-byte elements that must fit in what is left (so a corrupt count
    /// cannot allocate).
    pub fn count(&mut self, elem: usize, what: &str) -> CdrResult<usize> {
        let n = self.u32(what)? as usize;
        if n.saturating_mul(elem) > self.data.len() - self.pos {
            return Err(format!("{what}: {n} elements do not fit in the message"));
        }
        Ok(n)
    }
}
