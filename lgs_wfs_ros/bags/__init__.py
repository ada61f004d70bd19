"""MCAP bags in rosbag2's layout, without ROS: CDR codecs, writer, reader, recovery, joins.

See docs/bags.md for the file layout and the recovery command.
"""

from .cdr import decode_image, decode_string, encode_image, encode_string, peek_stamp
from .errors import BagError, BagExistsError, BagWriteError
from .join import Join, join_by_stamp
from .reader import BagReader
from .recovery import recover, recover_command
from .schema import message_definition, qos_yaml, type_hash
from .subapertures import read_subapertures
from .writer import BagWriter

__all__ = ["BagError", "BagExistsError", "BagReader", "BagWriteError", "BagWriter", "Join",
           "decode_image", "decode_string", "encode_image", "encode_string", "join_by_stamp",
           "message_definition", "peek_stamp", "qos_yaml", "read_subapertures", "recover", "recover_command", "type_hash"]
