"""The CAN side of a servo drive: CiA 301/402 protocol definitions, object dictionary, PDO codecs and the
CiA 402 master (:class:`drivers.drive.Drive`)."""
