//! Placeholder: the Ros1Bag reader is being written.

use std::path::Path;

use crate::{BagError, Container, Message, MessageRef, Topic};

/// A bag of this container format.
pub(crate) struct Ros1Bag {
    topics: Vec<Topic>,
}

impl Ros1Bag {
    /// Opens the file.
    pub(crate) fn open(path: &Path) -> Result<Self, BagError> {
        Err(BagError::NotABag {
            path: path.to_path_buf(),
            reason: "this container is not read yet".into(),
        })
    }
}

impl Container for Ros1Bag {
    fn topics(&self) -> &[Topic] {
        &self.topics
    }

    fn messages<'a>(
        &'a self,
        _topic: &Topic,
    ) -> Result<Box<dyn Iterator<Item = Result<Message, BagError>> + Send + 'a>, BagError> {
        Ok(Box::new(std::iter::empty()))
    }

    fn index(&self, _topic: &Topic) -> Result<Vec<MessageRef>, BagError> {
        Ok(Vec::new())
    }

    fn read(&self, at: &MessageRef) -> Result<Message, BagError> {
        Ok(Message {
            log_time_ns: at.log_time_ns,
            data: Vec::new(),
        })
    }
}
