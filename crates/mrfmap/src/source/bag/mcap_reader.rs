//! MCAP files read forward, a buffer at a time ([`mcap::sans_io::linear_reader::LinearReader`]):
//! one chunk is decompressed at a time, so a recording larger than memory streams. Schemas and
//! channels are kept as they come (they precede their messages); messages of the topics asked
//! for are handed on in file order. A file cut short (a robot lost power) is read up to its last
//! complete record: the reader says where it stopped and returns what came before.

use std::collections::HashMap;
use std::fs::File;
use std::io::Read;
use std::path::Path;

use mcap::McapError;
use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

use crate::error::{Error, Result};

/// Records (other than chunks) longer than this are corrupt: a depth image of the largest
/// size a frame may have in 32-bit floats is under 1 GiB.
const MAX_RECORD: usize = 1 << 30;

/// Calls `visit(topic, type, log_time_seconds, bytes)` for every message of `topics` (all when
/// empty) in `file`, in file order.
pub fn for_each(
    file: &Path,
    topics: &[&str],
    visit: &mut impl FnMut(&str, &str, f64, &[u8]) -> Result<()>,
) -> Result<()> {
    let mut input = File::open(file).map_err(|e| Error::io(file, e))?;
    let mut reader =
        LinearReader::new_with_options(LinearReaderOptions::default().with_record_length_limit(MAX_RECORD));
    let mut schemas: HashMap<u16, String> = HashMap::new();
    // Per channel: its topic and type, or `None` for a channel not asked for.
    let mut channels: HashMap<u16, Option<(String, String)>> = HashMap::new();
    let mut offset = 0u64;
    let bad = |e: McapError| Error::file(file, format!("corrupt MCAP: {e}"));
    while let Some(event) = reader.next_event() {
        let event = match event {
            Ok(event) => event,
            Err(McapError::UnexpectedEof) => {
                tracing::warn!(
                    "{}: cut short at byte {offset} (its recorder stopped?); read the messages before it",
                    file.display()
                );
                return Ok(());
            }
            Err(McapError::BadMagic) if offset <= 8 => return Err(Error::file(file, "not MCAP (no MCAP magic)")),
            Err(e) => return Err(bad(e)),
        };
        match event {
            LinearReadEvent::ReadRequest(need) => {
                let read = input.read(reader.insert(need)).map_err(|e| Error::io(file, e))?;
                reader.notify_read(read);
                offset += read as u64;
            }
            LinearReadEvent::Record { opcode, data } => match mcap::parse_record(opcode, data).map_err(bad)? {
                Record::Schema { header, .. } => {
                    schemas.insert(header.id, header.name);
                }
                Record::Channel(c) => {
                    let wanted = topics.is_empty() || topics.contains(&c.topic.as_str());
                    if wanted && c.message_encoding != "cdr" {
                        return Err(Error::file(
                            file,
                            format!("{}: message encoding {:?} is not CDR (a ROS 2 bag?)", c.topic, c.message_encoding),
                        ));
                    }
                    let msgtype = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                    channels.insert(c.id, wanted.then_some((c.topic, msgtype)));
                }
                Record::Message { header, data } => match channels.get(&header.channel_id) {
                    Some(Some((topic, msgtype))) => visit(topic, msgtype, header.log_time as f64 * 1e-9, &data)?,
                    Some(None) => {}
                    None => {
                        return Err(Error::file(
                            file,
                            format!("a message on channel {} before its channel", header.channel_id),
                        ));
                    }
                },
                _ => {}
            },
        }
    }
    Ok(())
}
