//! ROS 1 bags (format 2.0), read forward record by record with every length checked.
//!
//! A bag is `#ROSBAG V2.0\n` and then records: a header (length-prefixed `name=value` fields,
//! `op` saying what the record is) and length-prefixed data. Messages live in *chunk* records
//! (op 5; data uncompressed, `bz2` or `lz4`), which hold *connection* records (op 7: a topic
//! and, in the data, its type) and *message data* records (op 2: connection id, time, the
//! message). The index at the end is not needed to read forward, so a bag whose recorder was
//! killed (no index) or that was cut short (a robot lost power) reads up to its last complete
//! chunk: the reader says where it stopped and returns what came before. One chunk is in memory
//! at a time, so a bag of any size streams.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use crate::error::{Error, Result};

const MAGIC: &[u8] = b"#ROSBAG V2.0\n";
const OP_MESSAGE: u8 = 0x02;
const OP_CHUNK: u8 = 0x05;
const OP_CONNECTION: u8 = 0x07;

/// A chunk's uncompressed size may be at most this many times its stored size plus 64 KiB
/// (more is a corrupt header, refused before anything is allocated).
const MAX_EXPANSION: u64 = 256;

/// The fields of a record header.
struct Header<'a> {
    fields: Vec<(&'a [u8], &'a [u8])>,
}

impl<'a> Header<'a> {
    fn parse(bytes: &'a [u8]) -> std::result::Result<Self, String> {
        let mut fields = Vec::new();
        let mut rest = bytes;
        while !rest.is_empty() {
            let (field, tail) = block(rest).ok_or("a header field runs past its header")?;
            let eq = field.iter().position(|&b| b == b'=').ok_or("a header field has no '='")?;
            fields.push((&field[..eq], &field[eq + 1..]));
            rest = tail;
        }
        Ok(Header { fields })
    }

    fn get(&self, name: &str) -> Option<&'a [u8]> {
        self.fields.iter().find(|(n, _)| *n == name.as_bytes()).map(|f| f.1)
    }

    fn op(&self) -> Option<u8> {
        self.get("op").and_then(|v| v.first().copied())
    }

    fn u32(&self, name: &str) -> std::result::Result<u32, String> {
        let v = self.get(name).ok_or_else(|| format!("record has no {name} field"))?;
        Ok(u32::from_le_bytes(v.try_into().map_err(|_| format!("field {name} is not 4 bytes"))?))
    }

    fn text(&self, name: &str) -> std::result::Result<String, String> {
        let v = self.get(name).ok_or_else(|| format!("record has no {name} field"))?;
        String::from_utf8(v.to_vec()).map_err(|_| format!("field {name} is not UTF-8"))
    }
}

fn take_u32(bytes: &[u8]) -> Option<(u32, &[u8])> {
    let (head, tail) = bytes.split_first_chunk::<4>()?;
    Some((u32::from_le_bytes(*head), tail))
}

/// A length-prefixed block at the start of `bytes`, and what follows it.
fn block(bytes: &[u8]) -> Option<(&[u8], &[u8])> {
    let (len, tail) = take_u32(bytes)?;
    Some((tail.get(..len as usize)?, tail.get(len as usize..)?))
}

/// Calls `visit(topic, type, time (s), message)` for every message of `file` on `topics` (all
/// when empty), in file order; types are named the ROS 2 way (`sensor_msgs/msg/Image`).
pub fn for_each(
    file: &Path,
    topics: &[&str],
    visit: &mut impl FnMut(&str, &str, f64, &[u8]) -> Result<()>,
) -> Result<()> {
    let bad = |at: u64, m: &str| Error::file(file, format!("not a readable ROS 1 bag: at byte {at}: {m}"));
    let size = std::fs::metadata(file).map_err(|e| Error::io(file, e))?.len();
    let mut reader = BufReader::new(File::open(file).map_err(|e| Error::io(file, e))?);
    let mut magic = [0u8; MAGIC.len()];
    if reader.read_exact(&mut magic).is_err() || magic != MAGIC {
        return Err(Error::file(file, "not a ROS 1 bag: it does not start with \"#ROSBAG V2.0\""));
    }
    let mut connections: HashMap<u32, (String, String)> = HashMap::new();
    let mut at = MAGIC.len() as u64;
    let (mut header, mut data, mut chunk) = (Vec::new(), Vec::new(), Vec::new());
    loop {
        // A record: header length, header, data length, data.
        let start = at;
        let io = |e: std::io::Error| Error::io(file, e);
        let complete = read_block(&mut reader, &mut header, size, &mut at).map_err(io)?
            && read_block(&mut reader, &mut data, size, &mut at).map_err(io)?;
        if !complete {
            if start < size {
                tracing::warn!(
                    "{}: cut short: the record at byte {start} is incomplete (the file has {size} bytes); \
                     read the messages before it",
                    file.display()
                );
            }
            return Ok(());
        }
        let h = Header::parse(&header).map_err(|m| bad(start, &m))?;
        if h.op() != Some(OP_CHUNK) {
            continue; // the bag header, the index and chunk infos
        }
        let compression = h.text("compression").map_err(|m| bad(start, &m))?;
        let unpacked = h.u32("size").map_err(|m| bad(start, &m))? as u64;
        if unpacked > MAX_EXPANSION * data.len() as u64 + (1 << 16) {
            return Err(bad(start, &format!("a chunk of {} bytes claims {unpacked} bytes uncompressed", data.len())));
        }
        let records: &[u8] = match compression.as_str() {
            "none" => &data,
            "lz4" | "bz2" => {
                chunk.clear();
                let limit = unpacked + 1;
                let read = if compression == "lz4" {
                    lz4::Decoder::new(&data[..]).and_then(|d| d.take(limit).read_to_end(&mut chunk))
                } else {
                    bzip2::read::BzDecoder::new(&data[..]).take(limit).read_to_end(&mut chunk)
                };
                read.map_err(|e| bad(start, &format!("{compression} chunk does not decompress: {e}")))?;
                &chunk
            }
            other => return Err(bad(start, &format!("unknown chunk compression {other:?}"))),
        };
        if records.len() as u64 != unpacked {
            return Err(bad(start, &format!("chunk holds {} bytes, its header says {unpacked}", records.len())));
        }
        chunk_records(records, topics, &mut connections, visit).map_err(|e| match e {
            ChunkError::Bad(m) => bad(start, &format!("in the chunk: {m}")),
            ChunkError::Visit(e) => e,
        })?;
    }
}

enum ChunkError {
    Bad(String),
    Visit(Error),
}

/// The connection and message records of one chunk.
fn chunk_records(
    mut rest: &[u8],
    topics: &[&str],
    connections: &mut HashMap<u32, (String, String)>,
    visit: &mut impl FnMut(&str, &str, f64, &[u8]) -> Result<()>,
) -> std::result::Result<(), ChunkError> {
    while !rest.is_empty() {
        let (header, tail) = block(rest).ok_or_else(|| ChunkError::Bad("a record's header is cut off".into()))?;
        let (data, tail) = block(tail).ok_or_else(|| ChunkError::Bad("a record's data is cut off".into()))?;
        rest = tail;
        let h = Header::parse(header).map_err(ChunkError::Bad)?;
        match h.op() {
            Some(OP_CONNECTION) => {
                let id = h.u32("conn").map_err(ChunkError::Bad)?;
                let topic = h.text("topic").map_err(ChunkError::Bad)?;
                // `sensor_msgs/Image` -> `sensor_msgs/msg/Image`.
                let ty = Header::parse(data).and_then(|d| d.text("type")).map_err(ChunkError::Bad)?;
                let ty = ty.split_once('/').map_or(ty.clone(), |(p, t)| format!("{p}/msg/{t}"));
                connections.insert(id, (topic, ty));
            }
            Some(OP_MESSAGE) => {
                let id = h.u32("conn").map_err(ChunkError::Bad)?;
                let time = h
                    .get("time")
                    .and_then(|t| <[u8; 8]>::try_from(t).ok())
                    .ok_or_else(|| ChunkError::Bad("a message's time field is missing or not 8 bytes".into()))?;
                let sec = u32::from_le_bytes([time[0], time[1], time[2], time[3]]);
                let nsec = u32::from_le_bytes([time[4], time[5], time[6], time[7]]);
                let (topic, ty) = connections
                    .get(&id)
                    .ok_or_else(|| ChunkError::Bad(format!("message on connection {id} before its definition")))?;
                if topics.is_empty() || topics.contains(&topic.as_str()) {
                    visit(topic, ty, f64::from(sec) + f64::from(nsec) * 1e-9, data).map_err(ChunkError::Visit)?;
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// Reads a length-prefixed block into `buf`; `false` when the file ends before it does (or
/// its length runs past the file's `size`: a cut or corrupt file, nothing allocated for it).
fn read_block(reader: &mut impl Read, buf: &mut Vec<u8>, size: u64, at: &mut u64) -> std::io::Result<bool> {
    let ended = |e: std::io::Error| if e.kind() == std::io::ErrorKind::UnexpectedEof { Ok(false) } else { Err(e) };
    let mut len = [0u8; 4];
    if let Err(e) = reader.read_exact(&mut len) {
        return ended(e);
    }
    let len = u64::from(u32::from_le_bytes(len));
    if *at + 4 + len > size {
        return Ok(false);
    }
    buf.clear();
    buf.resize(len as usize, 0);
    if let Err(e) = reader.read_exact(buf) {
        return ended(e);
    }
    *at += 4 + len;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// A message as read: topic, type, time (s), bytes.
    type Message = (String, String, f64, Vec<u8>);

    fn field(name: &str, value: &[u8]) -> Vec<u8> {
        let mut f = ((name.len() + 1 + value.len()) as u32).to_le_bytes().to_vec();
        f.extend_from_slice(name.as_bytes());
        f.push(b'=');
        f.extend_from_slice(value);
        f
    }

    fn record(header: &[Vec<u8>], data: &[u8]) -> Vec<u8> {
        let h: Vec<u8> = header.concat();
        let mut r = (h.len() as u32).to_le_bytes().to_vec();
        r.extend_from_slice(&h);
        r.extend_from_slice(&(data.len() as u32).to_le_bytes());
        r.extend_from_slice(data);
        r
    }

    /// A bag of two chunks (compressed as `compression`): connections `/a` (sensor_msgs/Image)
    /// and `/b`, three messages each, between a bag header and an index-like trailer.
    fn bag(compression: &str) -> (Vec<u8>, Vec<Message>) {
        let mut out = MAGIC.to_vec();
        out.extend(record(&[field("op", &[0x03]), field("index_pos", &0u64.to_le_bytes())], &[b' '; 16]));
        let mut expected = Vec::new();
        for c in 0..2u32 {
            let mut records = Vec::new();
            if c == 0 {
                for (id, topic, ty) in [(0u32, "/a", "sensor_msgs/Image"), (1, "/b", "std_msgs/String")] {
                    let data = field("type", ty.as_bytes());
                    records.extend(record(
                        &[
                            field("op", &[OP_CONNECTION]),
                            field("conn", &id.to_le_bytes()),
                            field("topic", topic.as_bytes()),
                        ],
                        &data,
                    ));
                }
            }
            for m in 0..3u32 {
                let id = m % 2;
                let (sec, nsec) = (100 + c * 10 + m, 250_000_000u32);
                let mut time = sec.to_le_bytes().to_vec();
                time.extend_from_slice(&nsec.to_le_bytes());
                let payload = vec![(c * 3 + m) as u8; 5 + m as usize];
                records.extend(record(
                    &[field("op", &[OP_MESSAGE]), field("conn", &id.to_le_bytes()), field("time", &time)],
                    &payload,
                ));
                let (topic, ty) = if id == 0 { ("/a", "sensor_msgs/msg/Image") } else { ("/b", "std_msgs/msg/String") };
                expected.push((topic.to_string(), ty.to_string(), f64::from(sec) + 0.25, payload));
            }
            let stored = match compression {
                "none" => records.clone(),
                "bz2" => {
                    let mut e = bzip2::write::BzEncoder::new(Vec::new(), bzip2::Compression::default());
                    e.write_all(&records).unwrap();
                    e.finish().unwrap()
                }
                _ => {
                    let mut e = lz4::EncoderBuilder::new().build(Vec::new()).unwrap();
                    e.write_all(&records).unwrap();
                    e.finish().0
                }
            };
            out.extend(record(
                &[
                    field("op", &[OP_CHUNK]),
                    field("compression", compression.as_bytes()),
                    field("size", &(records.len() as u32).to_le_bytes()),
                ],
                &stored,
            ));
        }
        out.extend(record(&[field("op", &[0x04]), field("ver", &1u32.to_le_bytes())], &[0; 12]));
        (out, expected)
    }

    fn read(bytes: &[u8], name: &str, topics: &[&str]) -> Result<Vec<Message>> {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let mut got = Vec::new();
        let r = for_each(&path, topics, &mut |t, ty, time, data| {
            got.push((t.to_string(), ty.to_string(), time, data.to_vec()));
            Ok(())
        });
        r.map(|()| got)
    }

    #[test]
    fn reads_every_message_of_every_compression() {
        for compression in ["none", "bz2", "lz4"] {
            let (bytes, expected) = bag(compression);
            assert_eq!(read(&bytes, "all.bag", &[]).unwrap(), expected, "{compression}");
            let only_b: Vec<_> = expected.iter().filter(|m| m.0 == "/b").cloned().collect();
            assert_eq!(read(&bytes, "b.bag", &["/b"]).unwrap(), only_b, "{compression}");
        }
    }

    /// A bag cut at any byte reads without error or panic, and gives the messages of its
    /// complete chunks: a prefix of the whole bag's.
    #[test]
    fn a_bag_cut_anywhere_reads_its_complete_chunks() {
        for compression in ["none", "lz4"] {
            let (bytes, expected) = bag(compression);
            let mut seen = std::collections::BTreeSet::new();
            for cut in MAGIC.len()..bytes.len() {
                let got = read(&bytes[..cut], "cut.bag", &[]).unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
                assert!(expected.starts_with(&got), "cut at {cut}: not a prefix");
                assert!(got.len().is_multiple_of(3), "cut at {cut}: whole chunks only, got {}", got.len());
                seen.insert(got.len());
            }
            assert_eq!(seen.into_iter().collect::<Vec<_>>(), vec![0, 3, 6], "{compression}");
        }
    }

    #[test]
    fn corrupt_bags_are_errors_that_say_where() {
        let e = read(b"#ROSBAG V1.2\nxxxx", "old.bag", &[]).unwrap_err().to_string();
        assert!(e.contains("old.bag") && e.contains("#ROSBAG V2.0"), "{e}");
        // A chunk whose header claims far more than its data could hold.
        let (bytes, _) = bag("lz4");
        let mut huge = bytes.clone();
        let at = huge.windows(5).position(|w| w == b"size=").unwrap() + 5;
        huge[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = read(&huge, "huge.bag", &[]).unwrap_err().to_string();
        assert!(e.contains("huge.bag") && e.contains("at byte") && e.contains("uncompressed"), "{e}");
        // A message before its connection.
        let (bytes, _) = bag("none");
        let mut orphan = bytes.clone();
        let at = orphan.windows(6).position(|w| w == b"topic=").unwrap();
        let conn = orphan[..at].windows(5).rposition(|w| w == b"conn=").unwrap() + 5;
        orphan[conn..conn + 4].copy_from_slice(&7u32.to_le_bytes());
        let e = read(&orphan, "orphan.bag", &[]).unwrap_err().to_string();
        assert!(e.contains("before its definition"), "{e}");
    }
}
