//! The encoder beside [`super::reader::Reader`]: values serialized the way it reads
//! them (ROS 2 CDR with its encapsulation header, or ROS 1). The ROS 2 node publishes
//! its map cloud with it, and the unit tests build messages by hand with it.

use crate::Encoding;

/// A message under construction.
pub(crate) struct Writer {
    pub(crate) out: Vec<u8>,
    /// Where the body starts (after the CDR encapsulation header).
    start: usize,
    big_endian: bool,
    aligned: bool,
}

impl Writer {
    /// CDR little-endian (`big_endian` false), CDR big-endian, or ROS 1.
    pub(crate) fn new(encoding: Encoding, big_endian: bool) -> Self {
        match encoding {
            Encoding::Cdr => Self {
                out: vec![0, u8::from(!big_endian), 0, 0],
                start: 4,
                big_endian,
                aligned: true,
            },
            Encoding::Ros1 => Self {
                out: Vec::new(),
                start: 0,
                big_endian: false,
                aligned: false,
            },
        }
    }

    fn value(&mut self, le: &[u8]) {
        if self.aligned {
            while !(self.out.len() - self.start).is_multiple_of(le.len()) {
                self.out.push(0);
            }
        }
        if self.big_endian {
            self.out.extend(le.iter().rev());
        } else {
            self.out.extend_from_slice(le);
        }
    }

    pub(crate) fn u8(&mut self, v: u8) {
        self.out.push(v);
    }
    pub(crate) fn bool(&mut self, v: bool) {
        self.out.push(u8::from(v));
    }
    pub(crate) fn u32(&mut self, v: u32) {
        self.value(&v.to_le_bytes());
    }
    pub(crate) fn i32(&mut self, v: i32) {
        self.value(&v.to_le_bytes());
    }
    #[cfg(test)] // IMU and pose messages are only written by tests.
    pub(crate) fn f64(&mut self, v: f64) {
        self.value(&v.to_le_bytes());
    }
    pub(crate) fn string(&mut self, s: &str) {
        let nul = usize::from(self.aligned);
        self.u32((s.len() + nul) as u32);
        self.out.extend_from_slice(s.as_bytes());
        if self.aligned {
            self.out.push(0);
        }
    }
    pub(crate) fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.out.extend_from_slice(b);
    }
    pub(crate) fn header(&mut self, sec: i32, nanosec: u32, frame: &str) {
        if !self.aligned {
            self.u32(0); // seq: not kept by kfmap
        }
        self.i32(sec);
        self.u32(nanosec);
        self.string(frame);
    }
}
